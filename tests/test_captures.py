"""The captures the project ships (captures/) decode cleanly and hold what captures/README.md says.

Read through the real command line (``python -m mbmon read ... --json``), the
way a user reads them. The expected session is written out here from the
manual (Table 46 PTP parameters, Tables 12-15 register map), not taken from
the generator script, so a wrong capture or a wrong decoder both fail.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from collections import Counter
from functools import cache
from pathlib import Path
from typing import Any

import pytest

CAPTURES = Path(__file__).resolve().parents[1] / "captures"
ADU_KINDS = ("request", "response", "exception")

# Table 46: PTP {A1 90, A2 0, A3 0, A4 0, A5 0, A6 0} Vel=50% Acc=100% TOOL[1] BASE[2], R201..R226
TABLE_46 = [0, 0, 24464, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 50, 100, 1, 2, 0, 0, 0, 0, 0, 0, 0, 0]

# The session of captures/README.md: (fc, address, count) of the 28 requests, in order.
POLL = [(4, 200, 1), (4, 524, 1), (4, 300, 12)]
REQUESTS = [
    (4, 100, 1), (6, 100, 1), (2, 0, 8), (5, 0, 1), (15, 300, 5), (1, 0, 8), (16, 200, 1),
    (16, 201, 26), (3, 200, 2), (6, 200, 1), *POLL * 5, (6, 200, 1), (3, 1000, 2), (5, 0, 1),
]
FC_ADUS = {1: 2, 2: 2, 3: 4, 4: 32, 5: 4, 6: 6, 15: 2, 16: 4}


def _a(deg: int) -> list[int]:
    """Low/high words (unsigned) of an angle in 0.001 degree, Appendix II."""
    v = deg & 0xFFFFFFFF
    return [v & 0xFFFF, v >> 16]


# joints read in the five polls: from {0,0,0,0,-90,0} to {90,0,0,0,0,0}, 1/5 per poll
JOINTS = [_a(18000 * k) + [0] * 6 + _a(-90000 + 18000 * k) + [0, 0] for k in (1, 2, 3, 4)]
JOINTS.append(_a(90000) + [0] * 10)


@cache
def read(*args: str) -> tuple[dict[str, Any], ...]:
    p = subprocess.run([sys.executable, "-m", "mbmon", "read", *args, "--json"],
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    return tuple(json.loads(line) for line in p.stdout.splitlines())


def adus(*args: str) -> list[dict[str, Any]]:
    return [r for r in read(*args) if r["kind"] in ADU_KINDS]


SOURCES = {
    "tcp": (str(CAPTURES / "hrss_ptp.pcap"),),
    "rtu-pcap": (str(CAPTURES / "hrss_rtu.pcap"),),
    "rtu-raw": ("--rtu-raw", str(CAPTURES / "hrss_rtu.bin")),
}


@pytest.mark.parametrize("source", SOURCES)
def test_decodes_without_noise_or_malformed_frames(source: str) -> None:
    records = read(*SOURCES[source])
    kinds = Counter(r["kind"] for r in records)
    assert kinds["noise"] == 0
    assert kinds["request"] == 28 and kinds["response"] + kinds["exception"] == 28
    assert kinds["exception"] == 1
    assert not [r for r in records if r["malformed"]]
    events = [r.get("event") for r in records if r["kind"] == "event"]
    if source == "tcp":
        assert events == ["connect", "disconnect"]
    else:
        assert events == []


@pytest.mark.parametrize("source", SOURCES)
def test_session_is_the_readme_s(source: str) -> None:
    frames = adus(*SOURCES[source])
    requests = [r for r in frames if r["kind"] == "request"]
    assert [(r["fc"], r["address"], r["count"]) for r in requests] == REQUESTS
    counts = Counter(r["fc"] for r in frames)
    assert dict(counts) == FC_ADUS
    assert {r["unit"] for r in frames} == {1}
    # strictly request, answer, request, answer ...: every answer paired with the request before
    for i in range(0, len(frames), 2):
        req, resp = frames[i], frames[i + 1]
        assert req["kind"] == "request" and resp["kind"] in ("response", "exception")
        assert resp["request_index"] == req["index"] and resp["latency_ms"] is not None
        assert resp["fc"] == req["fc"] and resp["tid"] == req["tid"]


@pytest.mark.parametrize("source", SOURCES)
def test_register_values_are_the_manual_s(source: str) -> None:
    frames = adus(*SOURCES[source])
    ptp = [r for r in frames if r["kind"] == "request" and r["fc"] == 16 and r["address"] == 201]
    assert [r["values"] for r in ptp] == [TABLE_46]
    assert ptp[0]["pdu"].startswith("10 00 C9 00 1A 34 00 00 00 00 5F 90 00 01")

    def answers(fc: int, address: int) -> list[Any]:
        return [frames[i + 1]["values"] for i in range(0, len(frames), 2)
                if (frames[i]["fc"], frames[i]["address"]) == (fc, address)]

    assert answers(4, 100) == [[100]]  # IR100 speed
    assert answers(2, 0) == [[0, 0, 0, 1, 0, 0, 0, 0]]  # SO4 Ready
    assert answers(1, 0) == [[1, 0, 0, 0, 0, 0, 0, 0]]  # SI1 Start on
    assert answers(3, 200) == [[0, 0]]
    assert answers(4, 200) == [[0], [0], [0], [0], [1]]  # IR200 command status: success
    assert answers(4, 524) == [[2], [2], [2], [2], [1]]  # IR524 Running, then Idle
    assert answers(4, 300) == JOINTS
    coil_writes = [r["pdu"] for r in frames if r["kind"] == "request" and r["fc"] == 5]
    assert coil_writes == ["05 00 00 FF 00", "05 00 00 00 00"]
    assert [r["pdu"] for r in frames if r["kind"] == "request" and r["fc"] == 15] == [
        "0F 01 2C 00 05 01 13"]
    exc = [r for r in frames if r["kind"] == "exception"]
    assert [(r["fc"], r["exception_code"], r["address"], r["pdu"]) for r in exc] == [
        (3, 2, 1000, "83 02")]


def test_tcp_capture_transport_and_ids() -> None:
    frames = adus(*SOURCES["tcp"])
    assert {r["transport"] for r in frames} == {"tcp"}
    assert [r["tid"] for r in frames if r["kind"] == "request"] == list(range(1, 29))
    assert {r["dst"] for r in frames if r["kind"] == "request"} == {"127.0.0.1:502"}
    assert len({r["stream"] for r in frames}) == 1


@pytest.mark.parametrize("source", ["rtu-pcap", "rtu-raw"])
def test_rtu_capture_crc_and_same_bytes_as_tcp(source: str) -> None:
    frames = adus(*SOURCES[source])
    assert {r["transport"] for r in frames} == {"rtu"}
    assert all(r["crc_ok"] is True and r["tid"] is None for r in frames)
    tcp = adus(*SOURCES["tcp"])
    assert [r["pdu"] for r in frames] == [r["pdu"] for r in tcp]


def test_raw_dump_is_the_pcap_s_bytes() -> None:
    """hrss_rtu.bin is exactly the link-type-147 records of hrss_rtu.pcap concatenated."""
    data = (CAPTURES / "hrss_rtu.pcap").read_bytes()
    magic, _, _, _, _, _, linktype = struct.unpack("<IHHiIII", data[:24])
    assert (magic, linktype) == (0xA1B2C3D4, 147)
    pos, body = 24, bytearray()
    while pos < len(data):
        incl = int.from_bytes(data[pos + 8:pos + 12], "little")
        body += data[pos + 16:pos + 16 + incl]
        pos += 16 + incl
    assert bytes(body) == (CAPTURES / "hrss_rtu.bin").read_bytes()
    assert len(body) == 594
