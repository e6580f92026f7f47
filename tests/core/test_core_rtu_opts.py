"""``read --rtu-raw`` with the view's options on the compiled core: ``--robot``, ``-c``,
the filters (``--unit --fc --address --grep --since --until --where``), every ``-t``
mode and ``--baud``, against the reference pipeline (the same command line run in
this process forced pure, :mod:`opts_diff`): a byte table of each option, the
project's dumps, generated buses and hypothesis-drawn option sets, text and JSON,
byte for byte (stdout, stderr with the summary, exit status)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
from core_diff import ROOT, require_core
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from opts_diff import Run, assert_same
from rtu_gen import generated_bus, paired_bus

from mbmon.protocol.rtu import encode_rtu

CAPTURES = ROOT / "captures"


def _covered(run: Run) -> bool:
    return "core: the compiled core read the input (RTU framing, pairing and lines)" in run.core


def assert_same_rtu(args: list[str | Path]) -> Run:
    """``read --rtu-raw ARGS`` by the core (which must take it) and forced pure: the
    same stdout bytes, stderr and exit status. The core's run."""
    require_core()
    fast = assert_same(["--rtu-raw", *args])
    assert _covered(fast), f"the core declined {args}, or another of its paths ran: {fast.core}"
    return fast


# ---------------------------------------------------------------- a byte table

_REQ, _ANS = "master → slave", "slave → master"
_RECV, _SEND = "Receive from client", "Send to client"

#: the bus of the table: (its bytes, the record numbers they make)
BUS = [
    encode_rtu(1, bytes.fromhex("03 00 64 00 02")),  # 0
    encode_rtu(1, bytes.fromhex("03 04 00 07 00 08")),  # 1
    encode_rtu(2, bytes.fromhex("06 00 C8 00 01")),  # 2 (3: its timeout, by the next request)
    encode_rtu(1, bytes.fromhex("01 00 0A 00 03")),  # 4
    encode_rtu(1, bytes.fromhex("81 02")),  # 5
    bytes.fromhex("00 FF"),  # 6: noise at the end, 7: the timeout of nothing (none pending)
]

_L = {
    0: f"#0  {_REQ}  [u1]  03 00 64 00 02  | Read Holding Registers 100..101",
    1: f"#1  {_ANS}  [u1]  03 04 00 07 00 08  | Read Holding Registers 100..101 = 7, 8",
    2: f"#2  {_REQ}  [u2]  06 00 C8 00 01  | Write Single Register 200 = 1",
    3: "#3  -- No response to Write Single Register (record #2)",
    4: f"#4  {_REQ}  [u1]  01 00 0A 00 03  | Read Coils 10..12",
    5: f"#5  {_ANS}  [u1]  81 02  | Exception 02 Illegal Data Address (Read Coils)",
    6: "#6  bus.bin  !! noise, 2 bytes (truncated frame at end of stream): 00 FF",
}

OPTIONS = [
    # (options, the records shown)
    ([], [0, 1, 2, 3, 4, 5, 6]),
    (["--unit", "2"], [2]),  # a timeout has no unit: filtered out as in the reference
    (["--fc", "1"], [4, 5]),
    (["--fc", "3,6"], [0, 1, 2]),
    (["--address", "101"], [0, 1]),
    (["--address", "11-300"], [0, 1, 2, 4, 5]),
    (["--grep", "coils"], [4, 5]),
    (["--grep", "noise"], [6]),
    (["--where", "exception or timeout"], [3, 5]),
    (["--where", "R100 == 7"], [1]),
    (["--since", "0s"], [0, 1, 2, 3, 4, 5, 6]),
    (["--until", "1s"], [0, 1, 2, 3, 4, 5, 6]),
    # a raw dump has no capture times: --since/--until let every record through
    (["--since", "2020-01-01 00:00:00"], [0, 1, 2, 3, 4, 5, 6]),
    (["--until", "2020-01-01 00:00:00", "--unit", "1"], [0, 1, 4, 5]),
    (["-c", "3"], [0, 1, 2]),
    (["-c", "4"], [0, 1, 2, 3, 4]),  # a timeout is no frame for -c
    (["--unit", "1", "-c", "3"], [0, 1, 4]),
    (["--grep", "register", "-c", "2"], [0, 1]),
    (["-t", "r"], [0, 1, 2, 3, 4, 5, 6]),
    (["-t", "ud"], [0, 1, 2, 3, 4, 5, 6]),
    (["-t", "e"], [0, 1, 2, 3, 4, 5, 6]),
    (["--baud", "9600"], [0, 1, 2, 3, 4, 5, 6]),
    (["--baud", "115200"], [0, 1, 2, 3, 4, 5, 6]),
]  # fmt: skip


@pytest.fixture(scope="module")
def bus(tmp_path_factory: pytest.TempPathFactory) -> Path:
    dump = tmp_path_factory.mktemp("rtu") / "bus.bin"
    dump.write_bytes(b"".join(BUS))
    return dump


@pytest.mark.parametrize(("options", "shown"), OPTIONS)
def test_each_option_as_a_byte_table(bus: Path, options: list[str], shown: list[int]) -> None:
    run = assert_same_rtu([bus, *options])
    assert run.out.decode().splitlines() == [_L[i] for i in shown]
    assert_same_rtu([bus, *options, "--json"])


def test_robot_names_the_bus_and_warns_when_it_is_not_there(bus: Path) -> None:
    """``--robot BUS`` (the dump's name): the robot serves the bus, its own labels; a
    robot named elsewhere: neutral labels and the summary's warning."""
    run = assert_same_rtu([bus, "--robot", "bus.bin"])
    lines = run.out.decode().splitlines()
    assert lines[0].startswith(f"#0  {_RECV}  [u1]") and lines[1].startswith(f"#1  {_SEND}  [u1]")
    assert "appears in no stream" not in run.err
    other = assert_same_rtu([bus, "--robot", "10.0.0.9"])
    assert other.out.decode().splitlines()[0] == _L[0]
    assert "the robot 10.0.0.9 (--robot) appears in no stream" in other.err
    assert_same_rtu([bus, "--robot", "bus.bin", "--json"])


def test_count_ends_the_summary_there(bus: Path) -> None:
    """``-c 2``: the run ends at the second frame, the summary is what came before (the
    noise at the end never seen); with ``-q`` nothing is written but the run ends too."""
    run = assert_same_rtu([bus, "-c", "2"])
    assert run.err.splitlines() == [
        "2 frames (1 requests, 1 answered, 0 exceptions, 0 unanswered, 0 unsolicited) on 1 streams"
    ]
    assert assert_same_rtu([bus, "-c", "2", "-q"]).out == b""


# ---------------------------------------------------------------- dumps and buses

_SETS = [
    ["--unit", "1,17"],
    ["--fc", "3,16,23"],
    ["--address", "0-99"],
    ["--grep", "no matching"],
    ["--where", "exception"],
    ["-c", "40"],
    ["--fc", "5", "-c", "7", "-q"],
    ["-t", "ad", "--robot", "bus.bin"],
    ["--baud", "19200", "-c", "25"],
]


@pytest.mark.parametrize("options", _SETS, ids=" ".join)
@pytest.mark.parametrize("name", ["hrss_rtu.bin", "sim_rtu.bin"])
def test_project_dumps(name: str, options: list[str]) -> None:
    assert_same_rtu([CAPTURES / name, *options])


@pytest.mark.parametrize("options", _SETS, ids=" ".join)
def test_generated_buses(tmp_path: Path, options: list[str]) -> None:
    """Buses with every kind of trouble (noise, broken CRCs, cut frames, unsolicited
    and foreign answers, broadcasts, malformed answers) and every function code."""
    dump = tmp_path / "bus.bin"
    dump.write_bytes(paired_bus(11, 300) + generated_bus(12, 200))
    assert_same_rtu([dump, *options])
    assert_same_rtu([dump, *options, "--json"])


_OPTION = st.one_of(
    st.lists(st.sampled_from([0, 1, 5, 17, 247]), min_size=1, max_size=3).map(
        lambda units: ["--unit", ",".join(map(str, units))]
    ),
    st.lists(st.sampled_from([1, 2, 3, 4, 5, 6, 8, 15, 16, 23, 43]), min_size=1, max_size=3).map(
        lambda fcs: ["--fc", ",".join(map(str, fcs))]
    ),
    st.tuples(st.integers(0, 300), st.integers(0, 300)).map(
        lambda ab: ["--address", f"{min(ab)}-{max(ab)}"]
    ),
    st.sampled_from(["coil", "noise", "exception", "no response", "= 0", "crc"]).map(
        lambda text: ["--grep", text]
    ),
    st.sampled_from(["request", "response", "timeout or noise", "crc", "latency > 1ms"]).map(
        lambda expr: ["--where", expr]
    ),
    st.integers(1, 60).map(lambda n: ["-c", str(n)]),
    st.sampled_from(["a", "ad", "r", "e", "u", "ud"]).map(lambda mode: ["-t", mode]),
    st.sampled_from(["bus.bin", "other"]).map(lambda name: ["--robot", name]),
    st.sampled_from(["1200", "9600", "115200"]).map(lambda baud: ["--baud", baud]),
    st.just(["-q"]),
    st.just(["--json"]),
)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.integers(0, 2**16), st.lists(_OPTION, min_size=1, max_size=4))
def test_drawn_options_on_generated_buses(seed: int, drawn: list[list[str]]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        dump = Path(tmp) / "bus.bin"
        dump.write_bytes(paired_bus(seed, 120))
        options = [word for option in drawn for word in option]
        assert_same_rtu([dump, *options])
