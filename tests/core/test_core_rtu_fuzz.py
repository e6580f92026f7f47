"""Mutated RTU bus dumps through the compiled RTU framer: it never crashes and never
raises, every byte comes out once (in a frame or a noise run), and it frames what the
reference ``RtuDecoder`` frames, out of the same calls.

``MBMON_FUZZ_RUNS`` sets how many mutations (default 300), ``MBMON_FUZZ_SEED`` the
seed; ``MBMON_FUZZ_DIFF=0`` skips the comparison with the reference (the
AddressSanitizer run in CI: many mutations, memory safety and the byte count only).
The seed and the case are in every failure message.
"""

from __future__ import annotations

import os
import random
import struct

from core_diff import ROOT
from rtu_gen import chunked, generated_bus, libmodbus_bus, make_core, run, same
from test_core_fuzz import mutate

from mbmon.model import Direction

RUNS = int(os.environ.get("MBMON_FUZZ_RUNS", "300"))
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")


def _seeds() -> list[bytes]:
    seeds = [(ROOT / "captures" / name).read_bytes() for name in ("hrss_rtu.bin", "sim_rtu.bin")]
    seeds += [libmodbus_bus(), generated_bus(1, 60), generated_bus(2, 60)]
    return [s[:4000] for s in seeds]


def _accounted(data: bytes, steps: list[tuple[object, ...]], silence: float | None) -> None:
    """Every byte fed comes out once: the packed output's frames plus the noise runs."""
    framer = make_core(Direction.BUS, silence)
    out = 0
    for step in steps:
        if step[0] == "feed":
            framer.push(step[1], step[2])
        elif step[0] == "tick":
            framer.push_tick(step[1])
        else:
            framer.push_flush(step[1])
        records, raw, noise = framer.take()
        assert len(records) % 16 == 0
        packed = struct.iter_unpack("<BBHId", records)
        lengths = [length for kind, _, length, _, _ in packed if kind < 2]
        assert sum(lengths) == len(raw)
        out += len(raw) + sum(len(n.raw) for n in noise)
    assert out == len(data) and framer.buffered == 0


def test_mutated_rtu_dumps() -> None:
    make_core()
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed)
    seeds = _seeds()
    for case in range(RUNS):
        data = mutate(rng.choice(seeds), rng)
        if rng.random() < 0.3:
            data = mutate(data, rng)
        cuts = sorted({rng.randrange(len(data) + 1) for _ in range(rng.randint(0, 12))})
        steps = chunked(data, cuts, ts=lambda i: 5.0 + i)
        silence = 0.5 if case % 3 == 0 else None
        if silence is not None:  # a tick between reads now and then: settles what waits
            ticked: list[tuple[object, ...]] = []
            for i, step in enumerate(steps):
                ticked += [step, ("tick", 5.6 + i)] if i % 2 and step[0] == "feed" else [step]
            steps = ticked
        try:
            _accounted(data, steps, silence)
            if DIFF:
                same(steps, Direction.BUS, silence)
            elif case % 2:
                run(make_core(Direction.S2C), steps)
        except Exception as exc:  # the seed and case make the failure repeatable
            raise AssertionError(f"seed {seed} case {case}: {exc!r}") from exc
