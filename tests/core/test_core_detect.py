"""Port detection (``read``'s default) and the core: the core's first pass feeds the
reference's own port detector every TCP segment on ports not named, exactly as the
reference dissector feeds it. Where detection finds nothing (web, SSH, random bytes,
MBAP-looking requests nobody answers, over IPv4 and IPv6), the core reads the capture
and writes the reference's bytes; where it finds Modbus, the core declines before
writing anything."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from core_diff import assert_same, require_core, with_core
from gen import T0, adus, every_function_pair, write_frames

from mbmon.io.pcap import TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request

KINDS = ("http", "random", "mbap-unanswered", "mbap-cut", "mbap-answered")


def _other_payloads(kind: str, rng: random.Random) -> list[tuple[bool, bytes]]:
    """What a connection on a port nobody named carries, by kind."""
    if kind == "http":
        return [
            (True, b"GET /status HTTP/1.1\r\nHost: cell\r\n\r\n"),
            (False, b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\nok"),
        ] * 3
    if kind == "random":
        return [(rng.random() < 0.5, rng.randbytes(rng.randint(1, 300))) for _ in range(8)]
    request = encode_adu(7, 1, encode_read_request(3, 0, 4))
    if kind == "mbap-unanswered":  # requests, and an answer that is no MBAP
        return [(True, request), (False, b"\x15\x03\x03\x00\x02"), (True, request)]
    if kind == "mbap-cut":  # a header that chains, then a length that breaks it
        return [(True, request[:5] + b"\x00\x09" + request[7:]), (False, request)]
    return adus(every_function_pair()[:4])  # real Modbus: detection promotes it


def _capture(path: Path, kind: str, seed: int) -> Path:
    rng = random.Random(seed)
    v6 = rng.random() < 0.5
    other = TcpConversation(
        "[2001:db8::3]:40001" if v6 else "10.0.0.3:40001",
        f"[2001:db8::4]:{rng.choice([22, 80, 1502, 5020])}" if v6 else
        f"10.0.0.4:{rng.choice([22, 80, 1502, 5020])}",
    )  # fmt: skip
    modbus = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    first: list[bytes] = modbus.open()
    second: list[bytes] = other.open() if rng.random() < 0.7 else []  # or begun before
    for c, data in adus(every_function_pair()[:8]):
        first.append(modbus.send(c, data))
    for c, data in _other_payloads(kind, rng):
        second.append(other.send(c, data))
    frames: list[bytes] = []
    while first or second:  # interleaved at random, each connection in its own order
        take = first if (first and (not second or rng.random() < 0.5)) else second
        frames.append(take.pop(0))
    return write_frames(path, [(T0 + i * 0.001, f) for i, f in enumerate(frames)])


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("seed", range(6))
def test_core_reads_what_detection_leaves_alone(tmp_path: Path, kind: str, seed: int) -> None:
    require_core()
    path = _capture(tmp_path / f"{kind}-{seed}.pcap", kind, seed)
    if kind == "mbap-answered":
        _, _, why = with_core(path, as_json=False, detect=True)
        assert why is not None and why.startswith("Modbus found by port detection"), why
        return
    assert_same(path, covered=True, detect=True)
