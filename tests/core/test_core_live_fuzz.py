"""Mutated packet batches through the core's streaming entry: it never crashes and
never raises (what it does not cover hands the run over), and it writes what
``sniff``'s reference wiring writes for the same batches and ticks.

Mutations work on the packets (bytes flipped, a field set to an extreme, cut,
doubled), on their order (swapped, dropped, repeated) and on the batching and
ticks. ``MBMON_FUZZ_RUNS`` (default 300; a third of it here, each case runs two
hubs), ``MBMON_FUZZ_DIFF=0`` (only memory safety: the AddressSanitizer run in CI)
and ``MBMON_FUZZ_SEED`` as in ``test_core_fuzz.py``.
"""

from __future__ import annotations

import itertools
import os
import random
import tempfile
from pathlib import Path

from core_diff import ROOT, require_core
from gen import (
    T0,
    adus,
    every_function_pair,
    noisy_stream,
    reordered_conversation,
    udp_exchange,
    write_conversation,
)
from live_diff import Packet, Step, packets_of, reference, with_core
from test_core_fuzz import mutate

RUNS = max(1, int(os.environ.get("MBMON_FUZZ_RUNS", "300")) // 3)
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")


def _seeds(tmp: Path) -> list[list[Packet]]:
    seeds = [packets_of(ROOT / "captures" / name) for name in ("demo.pcap", "hrss_ptp.pcap")]
    stream = adus(every_function_pair())
    seeds.append(packets_of(write_conversation(tmp / "a.pcap", stream)))
    seeds.append(packets_of(write_conversation(tmp / "b.pcap", stream, linktype=113)))
    times = list(itertools.accumulate(0.3 + 0.95 * (i % 3 == 1) for i in range(len(stream))))
    slow = write_conversation(
        tmp / "c.pcap", stream, times=[T0 + t for t in times], handshake=False, close=None
    )
    seeds.append(packets_of(slow))
    # what the live entry keeps since it reads what the file entry reads: noise and
    # length 255 (over IPv6 too), holes, out of order and a replaced connection, UDP
    seeds.append(packets_of(write_conversation(tmp / "n.pcap", noisy_stream(4), step=0.2)))
    seeds.append(packets_of(reordered_conversation(tmp / "r.pcap", 3, replace=True)))
    seeds.append(packets_of(udp_exchange(tmp / "u.pcap", noisy_stream(8))))
    from test_core_live_net import _ipv6_noisy

    seeds.append(packets_of(_ipv6_noisy(tmp / "v6.pcap", 9)))
    return seeds


def mutate_packets(packets: list[Packet], rng: random.Random) -> list[Packet]:
    """Some packets' bytes mutated; or the order changed: a swap, a drop, a repeat."""
    out = list(packets)
    if not out:
        return out
    for _ in range(rng.randint(1, 4)):
        i = rng.randrange(len(out))
        ts, link, data = out[i]
        how = rng.randrange(5)
        if how <= 1:
            out[i] = (ts, link, mutate(data, rng))
        elif how == 2 and i + 1 < len(out):
            out[i], out[i + 1] = out[i + 1], out[i]
        elif how == 3 and len(out) > 1:
            del out[i]
        else:
            out.insert(i, (ts, link, data))
    return out


def _steps(packets: list[Packet], rng: random.Random) -> list[Step]:
    steps: list[Step] = []
    pos = 0
    while pos < len(packets):
        n = rng.choice([1, 1, 2, 3, 8, 64])
        batch = packets[pos : pos + n]
        pos += n
        steps.append(batch)
        if rng.random() < 0.3:
            steps.append(batch[-1][0] + rng.choice([0.0, 0.2, 1.0, 2.5, 400.0]))
    return steps


def test_mutated_packet_batches() -> None:
    require_core()
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed)
    covered = 0
    with tempfile.TemporaryDirectory() as tmp:
        seeds = _seeds(Path(tmp))
        for case in range(RUNS):
            packets = mutate_packets(rng.choice(seeds), rng)
            steps = _steps(packets, rng)
            as_json = bool(case & 1)
            try:
                got, got_summary, why = with_core(steps, as_json=as_json)
            except Exception as exc:  # the seed and case make the failure repeatable
                raise AssertionError(f"seed {seed} case {case}: the core raised {exc!r}") from exc
            covered += why is None
            if DIFF:
                want, want_summary = reference(steps, as_json=as_json)
                assert (got, got_summary) == (want, want_summary), (
                    f"seed {seed} case {case}: the core and the reference differ ({why})"
                )
    if RUNS >= 30:
        assert covered, "every mutation was handed over: the core ran on none of them"
