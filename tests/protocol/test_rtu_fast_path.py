"""The RTU framing loop's fast path decides exactly what ``_decide`` decides.

``RtuDecoder._decode`` accepts the common frame itself (preferred reading,
length from ``pdu.simple_length_rules``, CRC good) and hands everything else
to ``_decide``. With the rule tables emptied every byte goes through
``_decide``: the frames, noise runs (bytes, reasons, times) and statistics of
both must be the same for any bus traffic, chunking, direction and timing.
"""

from __future__ import annotations

import random
from itertools import pairwise

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mbmon.model import Direction, Frame, Noise, Stream, Transport
from mbmon.protocol import rtu
from mbmon.protocol.rtu import RtuDecoder, encode_rtu

BUS = Stream(1, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0")
PDUS = [
    (bytes.fromhex("0300100002"), bytes.fromhex("030400010002")),
    (bytes.fromhex("0100000009"), bytes.fromhex("0102ff01")),
    (bytes.fromhex("0f0000000a02ff03"), bytes.fromhex("0f0000000a")),
    (bytes.fromhex("10000100020400010002"), bytes.fromhex("1000010002")),
    (bytes.fromhex("0600010203"), bytes.fromhex("0600010203")),
    (bytes.fromhex("0500ffff00"), bytes.fromhex("8502")),
    (bytes.fromhex("0800000102"), bytes.fromhex("0800000102")),  # scanned (echo)
    (bytes.fromhex("2b0e0100"), bytes.fromhex("2b0e01010000010003414243")),  # scanned answer
    (bytes.fromhex("4101020304"), bytes.fromhex("41050607")),  # user code: scanned
    (bytes.fromhex("1700010002000300010200aa"), bytes.fromhex("170400010002")),
    (bytes.fromhex("0800010000"), bytes.fromhex("0800010000")),
]


def bus_bytes(seed: int, n: int) -> bytes:
    rng = random.Random(seed)
    parts = []
    for _ in range(n):
        req, resp = rng.choice(PDUS)
        unit = rng.choice((0, 1, 2, 17))
        r = rng.random()
        if r < 0.1:
            parts.append(rng.randbytes(rng.randint(1, 6)))
        elif r < 0.15:
            bad = bytearray(encode_rtu(unit, req))
            bad[-1] ^= 0x5A
            parts.append(bytes(bad))
        parts.append(encode_rtu(unit, req))
        if rng.random() < 0.9:
            parts.append(encode_rtu(unit, resp))
    return b"".join(parts)


def decode(data: bytes, cuts: list[int], direction: Direction, baud: int | None) -> list:
    d = RtuDecoder(BUS, direction, baudrate=baud, silence=0.5)
    out: list[Frame | Noise] = []
    points = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    ts = 0.0
    for i, (a, b) in enumerate(pairwise(points)):
        ts += 0.0001 if i % 3 else 0.01
        out += d.feed(data[a:b], ts)
        if i % 5 == 4:
            out += d.tick(ts + 0.005)
    out += d.flush(ts + 1)
    return [*out, dict(d.stats)]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.integers(0, 10**6),
    st.integers(1, 40),
    st.lists(st.integers(0, 10**4), max_size=30),
    st.sampled_from([Direction.BUS, Direction.C2S, Direction.S2C]),
    st.sampled_from([None, 9600, 115200]),
)
def test_fast_path_decides_as_decide(
    seed: int, n: int, cuts: list[int], direction: Direction, baud: int | None
) -> None:
    data = bus_bytes(seed, n)
    fast = decode(data, cuts, direction, baud)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rtu, "_REQ_RULES", {})
        mp.setattr(rtu, "_RESP_RULES", {})
        slow = decode(data, cuts, direction, baud)
    assert fast == slow


def test_fast_path_takes_the_common_frames() -> None:
    data = b"".join(encode_rtu(1, p) for pair in PDUS[:6] for p in pair)
    with pytest.MonkeyPatch.context() as mp:
        calls = []
        mp.setattr(RtuDecoder, "_decide", lambda *a: calls.append(a) or (0, False, "x"))
        out = RtuDecoder(BUS).feed(data, 0.0)
    assert len(out) == 12 and all(isinstance(f, Frame) for f in out)
    assert calls == []  # none of them needed _decide
