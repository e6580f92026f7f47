"""Mutated captures of what the network layers bring (noise, holes and reordered
segments, IPv6 with extension headers, Modbus/UDP) through the core: it never crashes,
never raises but to decline, and where it does not decline it writes what the
reference pipeline writes; the mutations reach the core's noise, gap and
reference-reassembly paths (checked on the counts).

``MBMON_FUZZ_RUNS`` sets how many mutations (here a fifth of it, at least 40: the
seeds are larger); ``MBMON_FUZZ_DIFF=0`` skips the comparison with the reference (the
AddressSanitizer run in CI). The seed of each case is in the failure message.
"""

from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path

from core_diff import reference, require_core
from gen import (
    T0,
    adus,
    every_function_pair,
    ipv6_segment,
    noisy_stream,
    reordered_conversation,
    udp_exchange,
    write_conversation,
    write_frames,
)
from test_core_fuzz import mutate

from mbmon import core
from mbmon.format import View
from mbmon.io.pcap import TcpConversation
from mbmon.io.pcap.packets import ACK, PSH
from mbmon.timefmt import TimeFormat

RUNS = max(40, int(os.environ.get("MBMON_FUZZ_RUNS", "300")) // 5)
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")


def _seeds(tmp: Path) -> list[bytes]:
    seeds = [
        reordered_conversation(tmp / "a.pcap", 1, replace=True).read_bytes(),
        reordered_conversation(tmp / "b.pcap", 2, close="rst", handshake=False).read_bytes(),
        write_conversation(tmp / "c.pcap", noisy_stream(5)).read_bytes(),
        udp_exchange(tmp / "d.pcap", noisy_stream(6)).read_bytes(),
        udp_exchange(
            tmp / "e.pcap", adus(every_function_pair()), client="[::1]:4000", server="[::2]:502"
        ).read_bytes(),
    ]
    conv = TcpConversation("[2001:db8::1]:40000", "[2001:db8::2]:502")
    frames = conv.open()
    for n, (client, adu) in enumerate(noisy_stream(7)):
        ext = ((0, b"\x01\x04\0\0\0\0"),) if n % 3 == 0 else ((60, b""), (44, bytes(6)))
        frames.append(ipv6_segment(conv, client, PSH | ACK, adu, extensions=ext))
    frames += conv.close(True)
    path = write_frames(tmp / "f.pcap", [(T0 + i * 0.01, f) for i, f in enumerate(frames)])
    seeds.append(path.read_bytes())
    return seeds


def _core_run(data: bytes, as_json: bool) -> tuple[bytes, str | None, dict]:
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
    return b"".join(chunks), run.declined, run.counts


def test_mutated_network_captures() -> None:
    require_core()
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "27"))
    rng = random.Random(seed)
    noisy = gaps = ran = 0
    with tempfile.TemporaryDirectory() as tmp:
        seeds = _seeds(Path(tmp))
        for case in range(RUNS):
            data = mutate(rng.choice(seeds), rng)
            if rng.random() < 0.3:
                data = mutate(data, rng)
            as_json = bool(case & 1)
            try:
                got, why, counts = _core_run(data, as_json)
            except Exception as exc:  # the seed and case make the failure repeatable
                raise AssertionError(f"seed {seed} case {case}: the core raised {exc!r}") from exc
            if why is not None:
                continue
            ran += 1
            noisy += counts["noise_records"] > 0
            gaps += counts["events"].get("gap", 0) > 0
            if DIFF:
                path = Path(tmp) / "m.pcap"
                path.write_bytes(data)
                want, _ = reference(path, as_json=as_json)
                assert got == want, f"seed {seed} case {case}: the core and the reference differ"
    assert ran and noisy and gaps, f"the mutations reached too little ({ran}, {noisy}, {gaps})"
