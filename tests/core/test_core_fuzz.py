"""Mutated captures through the core: it never crashes, never raises but to decline,
and where it does not decline it writes what the reference pipeline writes.

``MBMON_FUZZ_RUNS`` sets how many mutations (default 300); ``MBMON_FUZZ_DIFF=0`` skips
the comparison with the reference (the AddressSanitizer run in CI: many mutations,
only memory safety). The seed of each case is in the failure message.
"""

from __future__ import annotations

import itertools
import os
import random
import struct
import tempfile
from pathlib import Path

import pytest
from core_diff import ROOT, reference, require_core
from gen import T0, adus, every_function_pair, write_conversation

from mbmon import core
from mbmon.format import View
from mbmon.timefmt import TimeFormat

RUNS = int(os.environ.get("MBMON_FUZZ_RUNS", "300"))
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")


def _seeds(tmp: Path) -> list[bytes]:
    seeds = [(ROOT / "captures" / name).read_bytes() for name in ("demo.pcap", "hrss_ptp.pcap")]
    stream = adus(every_function_pair())
    seeds.append(write_conversation(tmp / "a.pcapng", stream, pcapng=True).read_bytes())
    seeds.append(write_conversation(tmp / "b.pcap", stream, linktype=113).read_bytes())
    # answers late and early around the 1 s timeout: ticks, timeouts at their due time
    times = list(itertools.accumulate(0.3 + 0.95 * (i % 3 == 1) for i in range(len(stream))))
    slow = write_conversation(
        tmp / "c.pcap", stream, times=[T0 + t for t in times], handshake=False, close=None
    )
    seeds.append(slow.read_bytes())
    return seeds


def mutate(data: bytes, rng: random.Random) -> bytes:
    """One of: flipped bytes, a field set to an extreme, a cut, a range removed or doubled."""
    buf = bytearray(data)
    if not buf:  # a cut at byte 0 leaves nothing to mutate again
        return data
    how = rng.randrange(5)
    if how == 0:
        for _ in range(rng.randint(1, 8)):
            buf[rng.randrange(len(buf))] ^= 1 << rng.randrange(8)
    elif how == 1:
        at = rng.randrange(max(1, len(buf) - 4))
        value = rng.choice([0, 1, 0xFF, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, len(buf)])
        buf[at : at + 4] = struct.pack("<I", value)[: len(buf[at : at + 4])]
    elif how == 2:
        del buf[rng.randrange(len(buf)) :]
    elif how == 3:
        a = rng.randrange(len(buf))
        del buf[a : a + rng.randint(1, 64)]
    else:
        a = rng.randrange(len(buf))
        piece = buf[a : a + rng.randint(1, 64)]
        buf[a:a] = piece
    return bytes(buf)


def _core_run(data: bytes, as_json: bool) -> tuple[bytes, str | None]:
    chunks: list[bytes] = []
    run = core.read_buffer(
        data,
        ports=frozenset({502}),
        timeout=1.0,
        view=View(time_format=TimeFormat("a")),
        as_json=as_json,
        write=chunks.append,
    )
    if run.declined is not None:
        assert not chunks
    return b"".join(chunks), run.declined


def test_mutated_captures() -> None:
    require_core()
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed)
    with tempfile.TemporaryDirectory() as tmp:
        seeds = _seeds(Path(tmp))
        ran = 0
        for case in range(RUNS):
            data = mutate(rng.choice(seeds), rng)
            if rng.random() < 0.3:
                data = mutate(data, rng)
            as_json = bool(case & 1)
            try:
                got, why = _core_run(data, as_json)
            except Exception as exc:  # the seed and case make the failure repeatable
                raise AssertionError(f"seed {seed} case {case}: the core raised {exc!r}") from exc
            if why is not None:
                continue
            ran += 1
            if DIFF:
                path = Path(tmp) / "m.pcap"
                path.write_bytes(data)
                want, _ = reference(path, as_json=as_json)
                assert got == want, f"seed {seed} case {case}: the core and the reference differ"
        if RUNS >= 100:
            assert ran, "the core declined every mutation: the fuzz test exercised nothing"


@pytest.mark.parametrize("size", [0, 1, 11, 12, 23, 24, 40])
def test_short_files(size: int) -> None:
    require_core()
    data = (ROOT / "captures" / "demo.pcap").read_bytes()[:size]
    _, why = _core_run(data, False)
    assert why is not None
