"""``read`` of a capture of an RTU bus (pcap or pcapng, link type 147: USER0) on the
compiled core (framing, pairing and the lines at the capture's times) against the
reference pipeline, the same command line run in this process forced pure
(:mod:`opts_diff`): the project's bus captures, generated ones (every function code,
noise, broken CRCs, cut frames, timeouts by time and by the next request, late and
unsolicited answers, records cut anywhere, silences, equal and backward times), with
the view's options, filters and ``-c``; hypothesis-drawn cuts and gaps; several
buses in one capture; and what the core declines (more than 64 buses, another link
type beside the bus, damage, ``--baud``)."""

from __future__ import annotations

import random
import tempfile
from pathlib import Path

import pytest
from core_diff import ROOT, require_core
from gen import T0
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from opts_diff import Run, assert_same, read_both
from rtu_gen import generated_bus, paired_bus

from mbmon.io.pcap import PcapngWriter, PcapWriter
from mbmon.protocol.rtu import encode_rtu

CAPTURES = ROOT / "captures"
COVERED = "core: the compiled core read the input (an RTU bus: framing, pairing and lines)"


def assert_bus_same(args: list[str | Path]) -> Run:
    """``read ARGS`` by the core (which must take it) and forced pure, byte for byte."""
    require_core()
    fast = assert_same(args)
    assert COVERED in fast.core, f"the core declined {args}: {fast.core}"
    return fast


def records(data: bytes, seed: int, *, t0: float = T0) -> list[tuple[float, bytes]]:
    """``data`` cut into records at random places, at times that move on by a byte's
    time, a pause between frames, a silence longer than the timeout, now and then
    not at all or backwards (a clock stepped back)."""
    rng = random.Random(seed)
    out: list[tuple[float, bytes]] = []
    ts, pos = t0, 0
    while pos < len(data):
        size = rng.choice((1, 2, 5, 8, 13, 40, 256))
        out.append((ts, data[pos : pos + size]))
        pos += size
        roll = rng.random()
        if roll < 0.5:
            ts += 0.0005 * size
        elif roll < 0.8:
            ts += rng.uniform(0.005, 0.3)
        elif roll < 0.9:
            ts += rng.uniform(1.0, 4.0)  # beyond the timeout and the framer's silence
        elif roll < 0.97:
            pass  # the same time
        else:
            ts -= rng.uniform(0.0, 0.5)
    return out


def write_bus(
    path: Path, recs: list[tuple[float, bytes]], *, pcapng: bool = False, empty: bool = False
) -> Path:
    """A capture of one bus (link type 147), pcap or pcapng (``empty``: one record
    without bytes too)."""
    if pcapng:
        with PcapngWriter(path) as w:
            w.add_interface(147)
            for ts, data in recs:
                w.write(ts, data)
            if empty:
                w.write(recs[-1][0], b"")
    else:
        with PcapWriter(path, 147) as w:
            for ts, data in recs:
                w.write(ts, data)
            if empty:
                w.write(recs[-1][0], b"")
    return path


# ---------------------------------------------------------------- the project's captures

_OPTIONS = [
    [],
    ["--json"],
    ["-t", "r"],
    ["-t", "ud", "--json"],
    ["--robot", "hrss_rtu.pcap"],
    ["--unit", "1", "--fc", "4"],
    ["--address", "300-400", "--json"],
    ["--grep", "input", "-c", "5"],
    ["--since", "0.5s", "--until", "1.2s"],
    ["--where", "latency > 50ms"],
    ["-c", "7", "-q"],
    ["--timeout", "0.05"],
]


@pytest.mark.parametrize("options", _OPTIONS, ids=" ".join)
@pytest.mark.parametrize("name", ["sim_rtu.pcap", "hrss_rtu.pcap"])
def test_project_bus_captures(name: str, options: list[str]) -> None:
    assert_bus_same([CAPTURES / name, *options])


# ---------------------------------------------------------------- a byte table


def test_timeouts_latency_and_late_answers_as_a_byte_table(tmp_path: Path) -> None:
    """A request answered in 0.5 ms (its latency), one left unanswered until the
    pairer's tick a second later (its timeout at its time plus the timeout), its late
    answer (unsolicited), one timed out by the next request, the end's timeout."""
    ask = encode_rtu(1, bytes.fromhex("03 00 64 00 02"))
    answer = encode_rtu(1, bytes.fromhex("03 04 00 07 00 08"))
    write = encode_rtu(2, bytes.fromhex("06 00 C8 00 01"))
    recs = [
        (T0, ask),
        (T0 + 0.0005, answer),
        (T0 + 1.0, ask),
        (T0 + 2.5, answer),  # after the timeout: no matching request
        (T0 + 3.0, write),
        (T0 + 3.2, ask),  # times the write out at its own time
        (T0 + 3.3, bytes.fromhex("00 FF")),  # noise; the end times the read out
    ]
    path = write_bus(tmp_path / "bus.pcap", recs)
    run = assert_bus_same([path, "-t", "r"])
    lines = run.out.decode().splitlines()
    assert lines == [
        "0.000000  master → slave  [u1]  03 00 64 00 02  | Read Holding Registers 100..101",
        "0.000500  slave → master  [u1]  03 04 00 07 00 08  "
        "| Read Holding Registers 100..101 = 7, 8 (0.5 ms)",
        "1.000000  master → slave  [u1]  03 00 64 00 02  | Read Holding Registers 100..101",
        "2.000000  -- No response to Read Holding Registers (record #2)",
        "2.500000  slave → master  [u1]  03 04 00 07 00 08  "
        "| Read Holding Registers = 7, 8 (no matching request)",
        "3.000000  master → slave  [u2]  06 00 C8 00 01  | Write Single Register 200 = 1",
        "3.200000  -- No response to Write Single Register (record #5)",
        "3.200000  master → slave  [u1]  03 00 64 00 02  | Read Holding Registers 100..101",
        "3.300000  bus.pcap  !! noise, 2 bytes (truncated frame at end of stream): 00 FF",
        "3.300000  -- No response to Read Holding Registers (record #7)",
    ]
    assert_bus_same([path, "--json"])


# ---------------------------------------------------------------- generated


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_generated_bus_captures(tmp_path: Path, seed: int) -> None:
    data = paired_bus(seed, 250) + generated_bus(seed + 10, 150)
    recs = records(data, seed)
    pcap = write_bus(tmp_path / "bus.pcap", recs)
    pcapng = write_bus(tmp_path / "bus.pcapng", recs, pcapng=True, empty=True)
    for path in (pcap, pcapng):
        text = assert_bus_same([path]).out
        for words in (b"No response to", b"(no matching request)", b"!! noise", b" ms)"):
            assert words in text
        for options in (["--json"], ["--timeout", "0.25"], ["-c", "60", "--unit", "1,17"]):
            assert_bus_same([path, *options])


def test_days_long_and_equal_times(tmp_path: Path) -> None:
    """Records days apart (the date in ``-t ad``), and a whole bus at one time."""
    data = paired_bus(21, 80)
    half = len(data) // 2
    recs = [(T0, data[:half]), (T0 + 3 * 86400.5, data[half:])]
    path = write_bus(tmp_path / "days.pcap", recs)
    for options in (["-t", "ad"], ["-t", "u", "--json"], ["-t", "e"]):
        assert_bus_same([path, *options])
    same = write_bus(tmp_path / "same.pcap", [(T0, data[i : i + 7]) for i in range(0, 400, 7)])
    assert_bus_same([same])


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**16), st.binary(max_size=40), st.booleans())
def test_drawn_cuts_and_gaps(seed: int, noise: bytes, pcapng: bool) -> None:
    data = paired_bus(seed, 40)
    cut = len(data) // 3
    recs = records(data[:cut] + noise + data[cut:], seed)
    with tempfile.TemporaryDirectory() as tmp:
        path = write_bus(Path(tmp) / "bus.pcap", recs, pcapng=pcapng)
        assert_bus_same([path, "--timeout", "0.5"])


# ---------------------------------------------------------------- several buses


def write_buses(path: Path, buses: list[list[tuple[float, bytes]]], *, quiet: int = -1) -> Path:
    """A pcapng of several buses, an interface each (link type 147), their records
    merged by time (each bus's in its own order); bus ``quiet`` gives an empty
    record first (its stream is made before it carries bytes)."""
    import heapq

    tagged = [[(ts, i, data) for ts, data in recs] for i, recs in enumerate(buses)]
    with PcapngWriter(path) as w:
        for _ in buses:
            w.add_interface(147)
        if quiet >= 0:
            w.write(buses[0][0][0], b"", interface=quiet)
        for ts, i, data in heapq.merge(*tagged, key=lambda r: r[0]):
            w.write(ts, data, interface=i)
    return path


def test_two_buses_as_a_byte_table(tmp_path: Path) -> None:
    """Each bus its stream (the second named ``NAME#IFACE``), its framer and its one
    pending request: a request on one bus is not timed out by the other's; the
    pairer's tick and the end time them out in the order the buses got a pending
    request (a bus whose request is replaced keeps its place: bus 0's newer request
    times out before bus 1's older one)."""
    ask1 = encode_rtu(1, bytes.fromhex("03 00 64 00 02"))
    ask2 = encode_rtu(2, bytes.fromhex("04 00 0A 00 01"))
    answer2 = encode_rtu(2, bytes.fromhex("04 02 00 2A"))
    bus0 = [(T0 + 0.1, ask1), (T0 + 0.5, ask1), (T0 + 3.0, ask1)]
    bus1 = [(T0, ask2[:3]), (T0 + 0.2, ask2[3:]), (T0 + 0.3, answer2), (T0 + 0.4, ask2)]
    path = write_buses(tmp_path / "two.pcapng", [bus0, bus1], quiet=1)
    run = assert_bus_same([path, "-t", "r"])
    holding, inputs = "Read Holding Registers", "Read Input Registers"
    assert run.out.decode().splitlines() == [
        f"0.000000  master → slave  [u1]  03 00 64 00 02  | {holding} 100..101",
        f"0.100000  master → slave  [u2]  04 00 0A 00 01  | {inputs} 10",
        f"0.200000  slave → master  [u2]  04 02 00 2A  | {inputs} 10 = 42 (100.0 ms)",
        f"0.300000  master → slave  [u2]  04 00 0A 00 01  | {inputs} 10",
        f"0.400000  -- No response to {holding} (record #0)",
        f"0.400000  master → slave  [u1]  03 00 64 00 02  | {holding} 100..101",
        f"1.400000  -- No response to {holding} (record #5)",
        f"1.300000  -- No response to {inputs} (record #3)",
        f"2.900000  master → slave  [u1]  03 00 64 00 02  | {holding} 100..101",
        f"2.900000  -- No response to {holding} (record #8)",
    ]
    assert "on 2 streams" in run.err
    assert_bus_same([path, "--json"])


@pytest.mark.parametrize("seed", [31, 32])
def test_generated_buses_in_one_capture(tmp_path: Path, seed: int) -> None:
    buses = [records(paired_bus(seed + i, 80), seed + i) for i in range(3)]
    path = write_buses(tmp_path / "three.pcapng", buses, quiet=2)
    text = assert_bus_same([path, "--timeout", "0.3"]).out
    assert b"three.pcapng#1  !! noise" in text or b"three.pcapng#2  !! noise" in text
    for options in (["--json"], ["--unit", "1", "-c", "40"], ["--robot", "three.pcapng#2"]):
        assert_bus_same([path, *options])


# ---------------------------------------------------------------- declines


def _declined(args: list[str | Path], why: str) -> None:
    require_core()
    fast = assert_same(args, covered=False)
    assert any(why in said for said in fast.core), fast.core


def test_what_the_core_declines_in_a_bus_capture(tmp_path: Path) -> None:
    data = paired_bus(5, 60)
    recs = records(data, 5)
    many = tmp_path / "many.pcapng"
    with PcapngWriter(many) as w:
        for i in range(65):
            w.add_interface(147)
            w.write(T0 + i, recs[i % len(recs)][1], interface=i)
    _declined([many], "more RTU buses than the core keeps")
    mixed = tmp_path / "mixed.pcapng"
    with PcapngWriter(mixed) as w:
        w.add_interface(147)
        w.add_interface(1)
        w.write(T0, recs[0][1])
        w.write(T0 + 1, bytes(60), interface=1)
    _declined([mixed], "link type 1 beside an RTU bus (USER0)")
    whole = write_bus(tmp_path / "bus.pcap", recs)
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(whole.read_bytes()[:-3])
    _declined([cut], "a damaged capture")
    _declined([whole, "--baud", "9600"], "--baud on a captured RTU bus")
    # and --debug-core says which decoder frames the bus then
    _declined([whole, "--baud", "9600"], "RTU framing: the reference decoder (a baud rate")
    _declined([whole, "--profile", "hrss"], "RTU framing: the compiled framer")
    _declined([whole, "-w", tmp_path / "x.mcap"], "-w with an RTU bus capture")
    noise = write_bus(tmp_path / "noise.pcap", [(T0, b"\x00\xff\x00")])
    _declined([noise], "no Modbus frames")


def test_a_compressed_bus_capture_and_rtu_port(tmp_path: Path) -> None:
    """A gzip-compressed bus capture is read on the core as the plain one; ``--rtu-port``
    (TCP and UDP ports) changes nothing in a capture of a bus."""
    import gzip

    packed = tmp_path / "sim_rtu.pcap.gz"
    packed.write_bytes(gzip.compress((CAPTURES / "sim_rtu.pcap").read_bytes()))
    assert_bus_same([packed, "--json"])
    assert_bus_same([CAPTURES / "sim_rtu.pcap", "--rtu-port", "502"])
    damaged = tmp_path / "damaged.pcap.gz"
    damaged.write_bytes(packed.read_bytes()[:-20])
    assert_same([damaged])


def test_a_bus_capture_among_several_inputs_is_declined() -> None:
    require_core()
    fast, pure = read_both([CAPTURES / "demo.pcap", CAPTURES / "sim_rtu.pcap"])
    assert fast.out == pure.out
    assert fast.core == ["core: declined (link type 147); the Python pipeline reads the input"]
