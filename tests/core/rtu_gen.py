"""RTU byte streams for the differential tests of the compiled RTU framer, and the
harness that drives it and the reference :class:`~mbmon.protocol.rtu.RtuDecoder`
call by call (``feed``, ``tick`` at every deadline, ``reset``, ``flush``)."""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from typing import Any

import pytest
from core_diff import require_core
from gen import every_function_pair
from rtu_corpus import BAD_CRC, BAD_REQUESTS, GOOD, RESPONSE_SHAPED, session

from mbmon import core
from mbmon.model import Direction, Stream, Transport
from mbmon.protocol.rtu import RtuDecoder, encode_rtu

STREAM = Stream(3, Transport.RTU, "bus", "bus", timed=False)

#: one step of a run: ("feed", data, ts), ("tick", now), ("reset", ts), ("flush", ts)
Step = tuple[Any, ...]


def make_core(direction: Direction = Direction.BUS, silence: float | None = None) -> Any:
    """The compiled framer (the test is skipped, or fails under MBMON_REQUIRE_CORE=1,
    without it)."""
    require_core()
    framer = core.rtu_decoder(STREAM, direction, silence=silence)
    if framer is None:
        why = core.rtu_decline(None)
        if core.available():
            pytest.fail(f"the reader is built but the RTU framer is not: {why}")
        pytest.skip(str(why))
    return framer


def run(dec: Any, steps: Sequence[Step]) -> list[list[Any]]:
    """What each step gave out (one list per step), and the deadlines and counts seen
    after it, so two decoders compare on *when* things come out too."""
    out: list[list[Any]] = []
    for step in steps:
        how = step[0]
        if how == "feed":
            got = dec.feed(step[1], step[2])
        elif how == "tick":
            got = dec.tick(step[1])
        elif how == "reset":
            got = dec.reset(step[1])
        else:
            got = dec.flush(step[1])
        out.append([*got, ("after", dec.buffered, dec.next_deadline(), dict(dec.stats))])
    return out


def same(steps: Sequence[Step], direction: Direction = Direction.BUS, silence: float | None = None):
    """Run ``steps`` through the reference and the compiled framer; assert equal output."""
    ref = run(RtuDecoder(STREAM, direction, silence=silence), steps)
    got = run(make_core(direction, silence), steps)
    if got != ref:
        for i, (a, b) in enumerate(zip(ref, got, strict=True)):
            if a != b:
                pairs = enumerate(zip(a, b, strict=False))
                j = next((k for k, (x, y) in pairs if x != y), min(len(a), len(b)))
                pytest.fail(
                    f"step {i} ({steps[i][0]}), item {j}: core "
                    f"{b[j] if j < len(b) else 'nothing'!r} != reference "
                    f"{a[j] if j < len(a) else 'nothing'!r} ({len(b)} and {len(a)} items)"
                )
    return ref


def chunked(data: bytes, cuts: Sequence[int], ts: Callable[[int], float] = float) -> list[Step]:
    """``data`` fed in pieces cut at ``cuts`` (sorted offsets), then flushed."""
    steps: list[Step] = []
    start = 0
    for i, cut in enumerate([*cuts, len(data)]):
        if cut > start:
            steps.append(("feed", data[start:cut], ts(i)))
            start = cut
    steps.append(("flush", ts(len(cuts) + 1)))
    return steps


def every_size(data: bytes, size: int) -> list[Step]:
    return chunked(data, list(range(size, len(data), size)))


def rtu_pairs(unit: int = 0x11) -> list[bytes]:
    """Request and answer of every function code of ``tests/core/gen.py`` as RTU ADUs."""
    out = []
    for req, resp in every_function_pair():
        out += [encode_rtu(unit, req), encode_rtu(unit, resp)]
    return out


def libmodbus_bus() -> bytes:
    """libmodbus's RTU unit-test session as one bus stream (its malformed CRC-valid
    requests, the response-shaped request, a bad CRC among them)."""
    parts = [raw for _, raw in session()]
    for req, resp in BAD_REQUESTS:
        parts += [req, resp]
    parts += [RESPONSE_SHAPED, BAD_CRC, GOOD]
    return b"".join(parts)


def generated_bus(seed: int, exchanges: int = 200) -> bytes:
    """A busy bus with every kind of trouble: every function code, exceptions,
    broadcasts, unknown codes (CRC scans), noise runs, broken CRCs, cut frames,
    libmodbus's malformed frames."""
    rng = random.Random(seed)
    pairs = rtu_pairs()
    parts: list[bytes] = []
    for _ in range(exchanges):
        roll = rng.random()
        if roll < 0.55:
            i = rng.randrange(0, len(pairs), 2)
            parts += pairs[i : i + 2]
        elif roll < 0.62:
            parts.append(bytes([0]) + rng.randbytes(rng.randint(0, 6)))  # line glitch
        elif roll < 0.68:
            bad = bytearray(rng.choice(pairs))
            bad[rng.randrange(len(bad))] ^= 1 << rng.randrange(8)
            parts.append(bytes(bad))
        elif roll < 0.72:
            frame = rng.choice(pairs)
            parts.append(frame[: rng.randrange(1, len(frame))])  # cut short
        elif roll < 0.76:
            parts += list(rng.choice(BAD_REQUESTS))
        elif roll < 0.80:
            vendor = bytes([0x41]) + rng.randbytes(rng.randint(0, 9))  # no predictable length
            parts.append(encode_rtu(rng.randint(1, 9), vendor))
        elif roll < 0.83:
            parts.append(encode_rtu(0, rng.choice(every_function_pair())[0]))  # broadcast
        elif roll < 0.86:
            parts.append(encode_rtu(rng.randint(1, 9), bytes([rng.randint(1, 0x7F) | 0x80, 2])))
        elif roll < 0.9:
            parts.append(rng.randbytes(rng.randint(1, 40)))
        else:
            unit = rng.randint(1, 247)
            fc = rng.choice((3, 4))
            n = rng.randint(1, 125)
            parts.append(encode_rtu(unit, bytes([fc, 0, 0, 0, n])))
            parts.append(encode_rtu(unit, bytes([fc, 2 * n]) + rng.randbytes(2 * n)))
    return b"".join(parts)


# ---------------------------------------------------------------- read --rtu-raw


def paired_bus(seed: int, exchanges: int = 200) -> bytes:
    """A bus that tries every RTU pairing rule: answered requests of every function
    code, exceptions, requests left unanswered (the next request times them out, the
    last one the end), answers nobody asked for, answers from another unit or of
    another code (unsolicited, the request stays pending), broadcasts, Diagnostics 04
    (never answered) and 00 (echoed), and now and then noise or a broken CRC."""
    rng = random.Random(seed)
    pairs = [
        (encode_rtu(unit, req), encode_rtu(unit, resp))
        for unit in (1, 0x11, 247)
        for req, resp in every_function_pair()
    ]
    parts: list[bytes] = []
    for _ in range(exchanges):
        req, resp = rng.choice(pairs)
        roll = rng.random()
        if roll < 0.5:
            parts += [req, resp]
        elif roll < 0.6:
            parts.append(req)  # unanswered
        elif roll < 0.67:
            parts.append(resp)  # nobody asked
        elif roll < 0.72:  # an answer from another unit, then the right one
            other = bytearray(resp[:-2])
            other[0] = (other[0] % 200) + 1
            parts += [req, encode_rtu(other[0], bytes(other[1:])), resp]
        elif roll < 0.77:
            parts.append(encode_rtu(0, every_function_pair()[rng.randrange(8)][0]))  # broadcast
        elif roll < 0.81:
            listen = encode_rtu(rng.choice((1, 9)), bytes.fromhex("08 00 04 00 00"))
            parts.append(listen)  # Force Listen Only: never answered, never pending
        elif roll < 0.85:
            echo = encode_rtu(5, bytes.fromhex("08 00 00 12 34"))
            parts += [echo, echo]
        elif roll < 0.89:
            unit, fc = rng.randint(1, 247), rng.choice((1, 2, 3, 4, 5, 6, 15, 16))
            parts += [req, encode_rtu(unit, bytes([fc | 0x80, rng.randint(0, 12)]))]
        elif roll < 0.93:
            parts.append(bytes([0]) + rng.randbytes(rng.randint(0, 5)))
        elif roll < 0.97:
            bad = bytearray(req)
            bad[-1] ^= 0x5A
            parts += [bytes(bad), resp]  # the request lost to a broken CRC
        else:
            n = rng.randint(1, 125)
            unit = rng.randint(1, 247)
            ask = encode_rtu(unit, bytes([3, 0, 0x10, 0, n]))
            short = encode_rtu(unit, bytes([3, 2 * n - 2]) + rng.randbytes(2 * n - 2))
            parts += [ask, short]  # a byte count that breaks its request (malformed)
    return b"".join(parts)


def _reference_rtu(stream: Stream, direction: Direction, config: Any) -> Any:
    return RtuDecoder(stream, direction, baudrate=config.baudrate, silence=config.settle_after)


def read_reference(
    path: Any, *, as_json: bool, timeout: float = 1.0, read_size: int = 4096
) -> tuple[bytes, str]:
    """``mbmon read --rtu-raw PATH`` by the reference pipeline (the reference
    ``RtuDecoder`` too, not the compiled framer), wired as ``read`` wires it: stdout's
    bytes and the summary's text."""
    import io
    from pathlib import Path

    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.pipeline import DecoderEntry, Pipeline, PipelineConfig
    from mbmon.sinks.console import ConsoleListener
    from mbmon.sinks.select import Selection
    from mbmon.sinks.summary import Summary
    from mbmon.sources.rawfile import read_rtu_raw
    from mbmon.timefmt import TimeFormat

    raw = io.BytesIO()
    out = io.TextIOWrapper(raw, encoding="utf-8", errors="backslashreplace", write_through=True)
    view = View(time_format=TimeFormat("a"))
    pipeline = Pipeline(None, PipelineConfig(timeout=timeout))
    name = Path(path).name
    pipeline.use_decoder(
        Stream(0, Transport.RTU, name, name, timed=False), DecoderEntry(_reference_rtu)
    )
    hub = Hub(pipeline)
    summary = Summary(None)
    hub.add_listener(Selection([ConsoleListener(out, view, as_json=as_json)], view))
    hub.add_listener(summary)
    hub.run_items(read_rtu_raw(path, read_size, stream_id=0))
    hub.close()
    out.flush()
    return raw.getvalue(), summary.text(timed=False)


def read_with_core(
    path: Any, *, as_json: bool, timeout: float = 1.0, quiet: bool = False, read_size: int = 4096
) -> tuple[bytes, str]:
    """``mbmon read --rtu-raw PATH`` by the compiled core (``quiet``: no lines, the
    counts only, as ``-q``): stdout's bytes and the summary's text."""
    from mbmon.format import View
    from mbmon.sinks.summary import Summary
    from mbmon.timefmt import TimeFormat

    require_core()
    chunks: list[bytes] = []
    run = core.read_rtu_file(
        str(path),
        timeout=timeout,
        view=View(time_format=TimeFormat("a")),
        as_json=as_json,
        write=None if quiet else chunks.append,
        read_size=read_size,
    )
    assert run.declined is None, run.declined
    summary = Summary(None)
    core.fill_rtu_summary(summary, run.counts)
    return b"".join(chunks), summary.text(timed=False)


def assert_read_same(path: Any, *, timeout: float = 1.0, read_size: int = 4096) -> bytes:
    """The core and the reference read the dump at ``path`` alike (in reads of
    ``read_size`` bytes), byte for byte, text and JSON, and the summary (also of a run
    without lines, ``-q``); the text."""
    text = b""
    kw: dict[str, Any] = {"timeout": timeout, "read_size": read_size}
    for as_json in (False, True):
        want, want_summary = read_reference(path, as_json=as_json, **kw)
        got, got_summary = read_with_core(path, as_json=as_json, **kw)
        if got != want:
            for i, (a, b) in enumerate(zip(got.splitlines(), want.splitlines(), strict=False)):
                assert a == b, f"{path} json={as_json} line {i}"
            assert len(got.splitlines()) == len(want.splitlines()), f"{path}: line count"
        assert got == want
        assert got_summary == want_summary
        if not as_json:
            text = got
            quiet, quiet_summary = read_with_core(path, as_json=False, quiet=True, **kw)
            assert quiet == b"" and quiet_summary == want_summary
    return text
