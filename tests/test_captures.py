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
    (4, 100, 1),
    (6, 100, 1),
    (2, 0, 8),
    (5, 0, 1),
    (15, 300, 5),
    (1, 0, 8),
    (16, 200, 1),
    (16, 201, 26),
    (3, 200, 2),
    (6, 200, 1),
    *POLL * 5,
    (6, 200, 1),
    (3, 1000, 2),
    (5, 0, 1),
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
    p = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", *args, "--json"], capture_output=True, text=True
    )
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
        assert resp["request_index"] == req["index"]
        # a raw dump has no timing: no latency is made up
        assert (resp["latency_ms"] is None) == (source == "rtu-raw")
        assert resp["fc"] == req["fc"] and resp["tid"] == req["tid"]


@pytest.mark.parametrize("source", SOURCES)
def test_register_values_are_the_manual_s(source: str) -> None:
    frames = adus(*SOURCES[source])
    ptp = [r for r in frames if r["kind"] == "request" and r["fc"] == 16 and r["address"] == 201]
    assert [r["values"] for r in ptp] == [TABLE_46]
    assert ptp[0]["pdu"].startswith("10 00 C9 00 1A 34 00 00 00 00 5F 90 00 01")

    def answers(fc: int, address: int) -> list[Any]:
        return [
            frames[i + 1]["values"]
            for i in range(0, len(frames), 2)
            if (frames[i]["fc"], frames[i]["address"]) == (fc, address)
        ]

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
        "0F 01 2C 00 05 01 13"
    ]
    exc = [r for r in frames if r["kind"] == "exception"]
    assert [(r["fc"], r["exception_code"], r["address"], r["pdu"]) for r in exc] == [
        (3, 2, 1000, "83 02")
    ]


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
        incl = int.from_bytes(data[pos + 8 : pos + 12], "little")
        body += data[pos + 16 : pos + 16 + incl]
        pos += 16 + incl
    assert bytes(body) == (CAPTURES / "hrss_rtu.bin").read_bytes()
    assert len(body) == 594


# --------------------------------------------------------------------------- captures of sim
#
# Recorded from mbmon's own simulator (captures/README.md, "Captures of sim").
# The expected answers are the manual's: Table 10 (the function codes HRSS
# serves), Tables 12-15 (the register map), Tables 16-43 (command status).

SIM_FUNCTIONS = (
    [  # (request PDU, answer PDU) of sim_functions.pcap, in order
        ("01 00 00 00 08", "01 01 00"),  # SI1..SI8 all off
        ("02 01 2C 00 08", "02 01 05"),  # DI[1], DI[3] on (docs/sim.md)
        ("03 00 64 00 01", "03 02 00 64"),  # R100 = 100 %
        ("04 00 64 00 01", "04 02 00 64"),  # IR100 = 100 %
        ("05 01 2C FF 00", "05 01 2C FF 00"),  # DO[1] ON, echoed
        ("06 00 64 00 5A", "06 00 64 00 5A"),  # R100 = 90, echoed
        ("0F 01 2C 00 05 01 13", "0F 01 2C 00 05"),  # DO[1..5] = 1 1 0 0 1
        ("10 00 00 00 02 04 00 01 00 02", "10 00 00 00 02"),  # SRR[1..2] = 1, 2
        ("01 01 2C 00 05", "01 01 13"),  # DO[1..5] read back
        ("03 00 00 00 02", "03 04 00 01 00 02"),  # SRR[1..2] read back
        ("04 00 64 00 01", "04 02 00 5A"),  # IR100 follows R100
    ]
    + [
        (pdu, f"{int(pdu[:2], 16) | 0x80:02X} 01")
        for pdu in (  # not in Table 10: exception 01
            "07",
            "08 00 00 12 34",
            "0B",
            "0C",
            "11",
            "15 09 06 00 01 00 00 00 01 00 00",
            "16 00 64 FF 00 00 00",
            "17 00 64 00 01 00 64 00 01 02 00 5A",
            "18 00 64",
            "2B 0E 01 00",
        )
    ]
)

SIM_EXCEPTIONS = [  # (unit, fc, address, exception code or None) of sim_exceptions.pcap
    (1, 0x2B, None, 1),
    (1, 4, 300, 2),
    (1, 4, 300, None),
    (1, 1, 256, 2),
    (1, 6, 50, 2),
    (1, 16, 1950, 2),
    (1, 6, 100, 3),
    (1, 16, 100, 3),
    (1, 6, 200, 3),
    (2, 4, 100, 0x0B),
    (1, 4, 100, None),
]


def pairs(*args: str) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(request, answer) of a one-request-at-a-time session, each answer checked to pair."""
    frames = adus(*args)
    result = []
    for i in range(0, len(frames), 2):
        req, resp = frames[i], frames[i + 1]
        assert req["kind"] == "request" and resp["request_index"] == req["index"]
        result.append((req, resp))
    return result


def commands(*args: str) -> list[tuple[str, str]]:
    """(phase, text) of every reconstructed HRSS command (``--profile hrss``)."""
    return [
        (r["command"]["phase"], r["command"]["text"])
        for r in read(*args, "--profile", "hrss")
        if r["kind"] == "command"
    ]


SIM_FILES = [
    "sim_functions.pcap",
    "sim_exceptions.pcap",
    "sim_fail.pcap",
    "demo.pcap",
    "sim_rtu.pcap",
]


@pytest.mark.parametrize("name", SIM_FILES)
def test_sim_captures_are_small_and_decode_cleanly(name: str) -> None:
    path = CAPTURES / name
    assert path.stat().st_size < 200_000
    records = read(str(path))
    kinds = Counter(r["kind"] for r in records)
    assert kinds["noise"] == 0 and not [r for r in records if r["malformed"]]
    assert kinds["request"] > 0 and kinds["request"] == kinds["response"] + kinds["exception"]
    assert {r["unit"] for r in records if r["kind"] in ADU_KINDS} <= {1, 2}


def test_sim_functions_every_code_and_its_answer() -> None:
    got = [(q["pdu"], a["pdu"]) for q, a in pairs(str(CAPTURES / "sim_functions.pcap"))]
    assert got == SIM_FUNCTIONS
    assert [q["tid"] for q, _ in pairs(str(CAPTURES / "sim_functions.pcap"))] == list(
        range(1, len(SIM_FUNCTIONS) + 1)
    )


def test_sim_exceptions_each_kind_of_refusal() -> None:
    got = [
        (q["unit"], q["fc"], q["address"], a["exception_code"])
        for q, a in pairs(str(CAPTURES / "sim_exceptions.pcap"))
    ]
    assert got == SIM_EXCEPTIONS


def test_sim_fail_a_failing_command_reads_status_2() -> None:
    path = str(CAPTURES / "sim_fail.pcap")
    status = [a["values"] for q, a in pairs(path) if (q["fc"], q["address"]) == (4, 200)]
    assert status == [[2, 0], [2, 200], [1, 103]]  # IR200..IR201: fail PTP, fail Get PR, success
    ptp = next(q["values"] for q, _ in pairs(path) if (q["fc"], q["address"]) == (16, 201))
    assert ptp[14] == 250  # R215: Vel=250 %, outside 1..200
    outcomes = [(phase, text) for phase, text in commands(path) if phase in ("fail", "success")]
    assert outcomes == [
        ("fail", "PTP {A1 90, A2 0, A3 0, A4 0, A5 0, A6 0} Vel=250% Acc=100% TOOL[1] BASE[2]"),
        ("fail", "Get PR[0]"),
        ("success", "Set Current TOOL[3]"),
    ]


def test_demo_capture_is_the_demo_s_traffic() -> None:
    path = str(CAPTURES / "demo.pcap")
    session = pairs(path)
    writes = [q["values"] for q, _ in session if (q["fc"], q["address"]) == (16, 201)]
    assert writes[0] == TABLE_46  # §5.4.5.2: PTP {A1 90} Vel=50% Acc=100% TOOL[1] BASE[2]
    assert [w[0] for w in writes] == [0, 1, 100, 200, 3]  # PTP, LIN, Set PR, Get PR, JOG
    guarded = [(q["pdu"], a["pdu"]) for q, a in session if q["fc"] == 5]
    assert guarded == [("05 00 00 FF 00", "85 01")]  # SI1 Start refused by the proxy's guard
    a1 = [
        a["values"][:2] for q, a in session if (q["fc"], q["address"], q["count"]) == (4, 300, 12)
    ]
    assert a1 == [[24464, 1]]  # A1 = 90° after the PTP
    pose = [a["values"] for q, a in session if (q["fc"], q["address"], q["count"]) == (4, 400, 12)]
    assert pose == [[27680, 65531, 37856, 4, 6784, 6, 48928, 2, 0, 0, 24464, 1]]  # after the LIN
    done = [text for phase, text in commands(path) if phase == "success"]
    assert [t.split(" ")[0] for t in done] == ["PTP", "LIN", "$PR[2]", "Get", "JOG"]
    assert {r["dst"] for r, _ in session} == {"127.0.0.1:502"}


@pytest.mark.parametrize("source", [("sim_rtu.pcap",), ("--rtu-raw", "sim_rtu.bin")])
def test_sim_rtu_the_program_over_a_pty(source: tuple[str, ...]) -> None:
    args = tuple(str(CAPTURES / a) if a.endswith((".pcap", ".bin")) else a for a in source)
    frames = adus(*args)
    assert {r["transport"] for r in frames} == {"rtu"} and all(r["crc_ok"] for r in frames)
    session = pairs(*args)
    requests = [(q["fc"], q["address"]) for q, _ in session]
    assert requests[:7] == [
        (4, 100),
        (16, 100),
        (2, 300),
        (15, 300),
        (16, 200),
        (16, 201),
        (16, 200),
    ]
    assert [q["values"] for q, _ in session if q["address"] == 201] == [TABLE_46]
    polls = [a["values"] for q, a in session if (q["fc"], q["address"]) == (4, 524)]
    assert [2] in polls and polls[-1] == [1]
    assert session[-1][1]["values"][:2] == [24464, 1]  # A1 = 90°


def test_sim_rtu_dump_is_the_pcap_s_bytes() -> None:
    data = (CAPTURES / "sim_rtu.pcap").read_bytes()
    assert struct.unpack("<IHHiIII", data[:24])[6] == 147
    pos, body = 24, bytearray()
    while pos < len(data):
        incl = int.from_bytes(data[pos + 8 : pos + 12], "little")
        body += data[pos + 16 : pos + 16 + incl]
        pos += 16 + incl
    assert bytes(body) == (CAPTURES / "sim_rtu.bin").read_bytes()
