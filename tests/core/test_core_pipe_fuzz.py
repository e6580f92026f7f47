"""Mutated classic pcaps through the pipe entry's own record parsing and its block path
(:meth:`mbmon.core.live.PipeCore.block`: ``_Live.pcap_records`` on the pipe's bytes
cut in random blocks, the hand-overs, the end and its damage): it never crashes nor
raises, and with the differential check on it writes what the reference pipeline
writes reading the same bytes (the ERROR line and the summary included), and parses
the records the reference's pump parses.

``MBMON_FUZZ_RUNS`` (a thirtieth of it here, see ``RUNS``),
``MBMON_FUZZ_DIFF=0`` (only memory safety: the AddressSanitizer run in CI) and
``MBMON_FUZZ_SEED`` as in ``test_core_fuzz.py``.
"""

from __future__ import annotations

import io
import os
import random
import tempfile
from pathlib import Path

from core_diff import ROOT, require_core
from gen import adus, every_function_pair, noisy_stream, reordered_conversation, write_conversation
from test_core_fuzz import mutate

from mbmon.format import View
from mbmon.hub import Hub
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.sinks.console import ConsoleListener
from mbmon.sinks.summary import Summary
from mbmon.sources.pcapfile import (
    READ_FAILURES,
    CaptureConfig,
    CaptureError,
    _pcap_pump,
    open_records,
    read_capture,
)
from mbmon.timefmt import TimeFormat

# a hub and the core's stage per case: a thirtieth of the runs asked (100 by default;
# 1,000 in CI's AddressSanitizer stage, which asks 30,000 of every fuzz file there)
RUNS = max(1, int(os.environ.get("MBMON_FUZZ_RUNS", "3000")) // 30)
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")


class _Kept(io.BytesIO):
    """stdout's bytes, kept when the console closes it."""

    def close(self) -> None:
        pass


def _wired(as_json: bool) -> tuple[Hub, io.BytesIO, Summary, View]:
    raw = _Kept()
    out = io.TextIOWrapper(raw, encoding="utf-8", errors="backslashreplace", write_through=True)
    view = View(time_format=TimeFormat("a"))
    hub = Hub(Pipeline(None, PipelineConfig(timeout=1.0)))
    summary = Summary(None)
    hub.add_listener(ConsoleListener(out, view, as_json=as_json, live=True))
    hub.add_listener(summary)
    return hub, raw, summary, view


def _reference(path: Path, as_json: bool) -> tuple[bytes, str, list[str]]:
    hub, raw, summary, _ = _wired(as_json)
    try:
        hub.run_items(read_capture(path, CaptureConfig(detect=True), new_stream=hub.new_stream))
    except CaptureError as exc:
        return b"", f"error: {exc}", []
    hub.close()
    return raw.getvalue(), summary.text(timed=True), hub.errors


def _with_pipe_entry(path: Path, as_json: bool, rng: random.Random) -> tuple[bytes, str, list[str]]:
    """The pipe entry's block path on ``path``'s bytes after the file header, in blocks
    of random sizes (no reader thread, no ticks: what a pipe read at once gives)."""
    from mbmon.core.live import PipeCore, _End, _end_pipe, add_counts
    from mbmon.sources.dissect import Dissector

    try:
        opened = open_records(path)
    except CaptureError as exc:
        return b"", f"error: {exc}", []
    inp, pump, raw_file = opened
    raw_file.close()
    if getattr(pump, "func", None) is not _pcap_pump:
        return _reference(path, as_json)  # pcapng: the pump's records (not this test's)
    hub, raw, summary, view = _wired(as_json)
    dissector = Dissector(
        CaptureConfig(detect=True),
        path.name,
        new_stream=hub.new_stream,
        idle_timeout=None,
        hole_timeout=None,
    )
    stage = PipeCore(
        ports=frozenset({502}),
        timeout=1.0,
        view=view,
        as_json=as_json,
        write=raw.write,
        new_stream=hub.new_stream,
        dissector=dissector,
        pipeline=hub.pipeline,
        detect=True,
    )
    stage.pcap(*pump.args[1:])
    stage.base = inp.base + inp.pos
    rest = path.read_bytes()[stage.base :]
    while rest and stage.damage is None:
        cut = rng.choice((1, 7, 16, 100, 1500, 1 << 20))
        items = stage.block(rest[:cut])
        rest = rest[cut:]
        if items:
            hub.feed_items(items)
    _end_pipe(stage, hub, _End(), inp, str(path))
    hub.finish()
    hub.close()
    add_counts(summary, stage.counts())
    return raw.getvalue(), summary.text(timed=True), hub.errors


def _pump_records(path: Path) -> tuple[list[tuple[float, int, bytes]], str | None]:
    """The records the reference's pump parses, and the damage that ended them."""
    _, pump, raw = open_records(path)
    got: list[tuple[float, int, bytes]] = []

    def packet(ts: float, link: int, _: int, buf: bytes, a: int, b: int, out: object) -> None:
        got.append((ts, link, buf[a:b]))

    try:
        for _ in pump(packet, []):
            pass
    except READ_FAILURES as exc:
        return got, str(exc)
    finally:
        raw.close()
    return got, None


def _seeds(tmp: Path) -> list[bytes]:
    stream = adus(every_function_pair())
    return [
        (ROOT / "captures" / "demo.pcap").read_bytes(),
        write_conversation(tmp / "a.pcap", stream).read_bytes(),
        write_conversation(tmp / "b.pcap", stream, linktype=113).read_bytes(),
        write_conversation(tmp / "n.pcap", noisy_stream(3), step=0.2).read_bytes(),
        reordered_conversation(tmp / "r.pcap", 5).read_bytes(),
    ]


def test_mutated_pcaps_through_the_pipe_entry() -> None:
    require_core()
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        seeds = _seeds(folder)
        path = folder / "case.pcap"
        for case in range(RUNS):
            data = mutate(rng.choice(seeds), rng)
            if rng.random() < 0.3:
                data = mutate(data, rng)
            path.write_bytes(data)
            as_json = bool(case & 1)
            where = f"seed {seed}, case {case}"
            try:
                got = _with_pipe_entry(path, as_json, random.Random(case))
            except Exception as exc:  # the seed and case make the failure repeatable
                raise AssertionError(f"{where}: {type(exc).__name__}: {exc}") from exc
            if DIFF:
                assert got == _reference(path, as_json), where


def test_the_core_parses_the_records_the_pump_parses() -> None:
    """``_Live.pcap_records`` (records out) against the reference's pump, on mutated
    pcaps cut at random: the same records, times and link types, the same end."""
    require_core()
    from mbmon.core import _reader
    from mbmon.sources.pcapfile import _MAX_RECORD

    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed + 1)
    live = _reader._Live(False, 1.0, frozenset({502}), None, None)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        seeds = _seeds(folder)
        path = folder / "case.pcap"
        for case in range(RUNS):
            data = mutate(rng.choice(seeds), rng)
            path.write_bytes(data)
            try:
                inp, pump, raw = open_records(path)
            except CaptureError:
                continue
            raw.close()
            if getattr(pump, "func", None) is not _pcap_pump:
                continue
            _, endian, divisor, link, snaplen, header = pump.args
            limit = min(max(snaplen, 262144), _MAX_RECORD)
            got: list[tuple[float, int, bytes, int]] = []
            buf, pos = b"", 0
            rest = data[inp.base + inp.pos :]
            stop = 0
            while rest and stop != 2:
                cut = rng.randrange(1, 300)
                buf, rest = buf[pos:] + rest[:cut], rest[cut:]
                pos = live.pcap_records(buf, 0, endian == ">", divisor, header, link, limit, got)
                stop = live.rec_stop
            expected, damage = _pump_records(path)
            assert [(ts, lt, b) for ts, lt, b, _ in got] == expected, f"seed {seed}, case {case}"
            left = len(buf) - pos
            assert (damage is None) == (left == 0 and stop != 2), (case, damage, left, stop)
