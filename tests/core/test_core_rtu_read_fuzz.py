"""Mutated RTU bus dumps read by the compiled core end to end (``read --rtu-raw``:
framing, pairing, text and JSON lines): never a crash, never an exception, and the
reference pipeline's bytes and summary.

``MBMON_FUZZ_RUNS`` sets how many mutations (default 40), ``MBMON_FUZZ_SEED`` the
seed; ``MBMON_FUZZ_DIFF=0`` skips the comparison with the reference (CI's
AddressSanitizer run: more mutations, memory safety only). The seed and the case are
in every failure message.
"""

from __future__ import annotations

import os
import random

from core_diff import ROOT
from rtu_gen import assert_read_same, generated_bus, libmodbus_bus, paired_bus, read_with_core
from test_core_fuzz import mutate

RUNS = int(os.environ.get("MBMON_FUZZ_RUNS", "40"))
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")


def _seeds() -> list[bytes]:
    seeds = [(ROOT / "captures" / name).read_bytes() for name in ("hrss_rtu.bin", "sim_rtu.bin")]
    seeds += [libmodbus_bus(), generated_bus(1, 60), paired_bus(2, 80), paired_bus(3, 80)]
    return [s[:5000] for s in seeds]


def test_mutated_dumps_read_alike(tmp_path) -> None:
    read_with_core(ROOT / "captures" / "sim_rtu.bin", as_json=False)  # skips without the core
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed)
    seeds = _seeds()
    dump = tmp_path / "bus.bin"
    for case in range(RUNS):
        data = mutate(rng.choice(seeds), rng)
        if rng.random() < 0.3:
            data = mutate(data, rng)
        dump.write_bytes(data)
        try:
            if DIFF:
                assert_read_same(dump, timeout=rng.choice((1.0, 0.01)))
            else:
                for as_json in (False, True):
                    got, _ = read_with_core(dump, as_json=as_json)
                    assert got or not data
        except Exception as exc:  # the seed and case make the failure repeatable
            raise AssertionError(f"seed {seed} case {case}: {exc!r}") from exc
