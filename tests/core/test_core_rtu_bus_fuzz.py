"""Mutated captures of RTU buses (pcap and pcapng, link type 147) read by the
compiled core (``read`` of a USER0 capture: the container, the bus's records framed,
paired and written at their times): never a crash, never an exception but a decline,
and the reference pipeline's bytes (stdout, the summary, the exit status).

``MBMON_FUZZ_RUNS`` sets how many mutations (default 40), ``MBMON_FUZZ_SEED`` the
seed; ``MBMON_FUZZ_DIFF=0`` skips the comparison with the reference (CI's
AddressSanitizer run: more mutations, memory safety only). The seed and the case are
in every failure message.
"""

from __future__ import annotations

import os
import random

from core_diff import ROOT, require_core
from opts_diff import read_both
from rtu_gen import generated_bus, paired_bus
from test_core_fuzz import mutate
from test_core_rtu_bus import records, write_bus, write_buses

from mbmon import core
from mbmon.format import View
from mbmon.timefmt import TimeFormat

RUNS = int(os.environ.get("MBMON_FUZZ_RUNS", "40"))
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")


def _seeds(tmp_path) -> list[bytes]:
    seeds = [(ROOT / "captures" / name).read_bytes() for name in ("hrss_rtu.pcap", "sim_rtu.pcap")]
    for seed, pcapng in ((1, False), (2, True)):
        recs = records(paired_bus(seed, 40) + generated_bus(seed, 30), seed)
        path = write_bus(tmp_path / f"seed{seed}.cap", recs, pcapng=pcapng, empty=True)
        seeds.append(path.read_bytes())
    buses = [records(paired_bus(seed, 30), seed) for seed in (3, 4, 5)]
    seeds.append(write_buses(tmp_path / "buses.pcapng", buses, quiet=1).read_bytes())
    return [s[:6000] for s in seeds]


def test_mutated_bus_captures_read_alike(tmp_path) -> None:
    require_core()
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed)
    seeds = _seeds(tmp_path)
    path = tmp_path / "bus.pcap"
    covered = 0
    buses = [paired_bus(seed, 30) for seed in (6, 7, 8)]
    for case in range(RUNS):
        if case % 3 == 2:  # a whole container of mutated buses: the framing and pairing
            mutated = [mutate(bus, rng) for bus in rng.sample(buses, rng.randint(1, 3))]
            recs = [records(bus, rng.randrange(1 << 16)) for bus in mutated if bus]
            if not recs:
                continue
            write_buses(path, recs)
        else:  # the container itself mutated
            data = mutate(rng.choice(seeds), rng)
            if rng.random() < 0.3:
                data = mutate(data, rng)
            path.write_bytes(data)
        try:
            if DIFF:
                fast, pure = read_both([path, *(["--json"] if case % 2 else ["-t", "ad"])])
                assert (fast.out, fast.err, fast.status) == (pure.out, pure.err, pure.status)
                covered += any("an RTU bus" in said for said in fast.core)
            else:
                for as_json in (False, True):
                    out: list[bytes] = []
                    view = View(time_format=TimeFormat("a"))
                    core.read_bus_file(
                        str(path), timeout=1.0, view=view, as_json=as_json, write=out.append
                    )
        except Exception as exc:  # the seed and case make the failure repeatable
            raise AssertionError(f"seed {seed} case {case}: {exc!r}") from exc
    assert not DIFF or RUNS < 20 or covered >= RUNS // 5  # the core read a good share
