"""``read``'s view options on the core: every ``-t`` mode and ``--robot`` labels, core
against forced pure, byte for byte (stdout text and JSON, stderr's summary and
warnings, the exit status), on the captures and on generated ones."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import pytest
from core_diff import REAL, ROOT, require_core
from gen import T0, adus, every_function_pair, write_conversation, write_frames
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from opts_diff import assert_same, ran_core, read_run

from mbmon.io.pcap import TcpConversation

OWN = sorted((ROOT / "captures").glob("*.pcap*"))
PUBLIC = sorted(REAL.glob("*.pcap*")) if REAL.is_dir() else []
MODES = ("r", "ad", "e", "u", "ud")
DEMO = ROOT / "captures" / "demo.pcap"


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def _ends(path: Path) -> tuple[str, str] | None:
    """The client and server endpoints of the first frame of a capture, or None."""
    first = read_run([path, "--json", "-c", "1", "-q"], pure=True)
    lines = [json.loads(line) for line in first.out.splitlines()]
    run = read_run([path, "--json", "-c", "1"], pure=True)
    for obj in [*lines, *(json.loads(line) for line in run.out.splitlines())]:
        if obj.get("kind") == "request":
            return obj["src"], obj["dst"]
        if obj.get("kind") in ("response", "exception"):
            return obj["dst"], obj["src"]
    return None


@pytest.mark.parametrize("path", OWN + PUBLIC, ids=lambda p: p.name)
def test_time_modes_and_robot_on_captures(path: Path) -> None:
    """Each capture in two ``-t`` modes (text, JSON) and with the robot as the server
    (by host), by its endpoint with a JSON line, and as the client."""
    i = (OWN + PUBLIC).index(path)
    assert_same([path, "-t", MODES[i % 5]])
    assert_same([path, "-t", MODES[(i + 2) % 5], "--json"])
    ends = _ends(path)
    if ends is None:
        return
    client, server = ends
    assert_same([path, "--robot", server.rsplit(":", 1)[0]])
    assert_same([path, "--robot", server, "--json", "-t", "r"])
    assert_same([path, "--robot", client.rsplit(":", 1)[0], "-t", MODES[(i + 4) % 5]])


def test_the_core_covers_them() -> None:
    """The view options no longer keep a covered capture off the core."""
    for args in (["-t", "r"], ["-t", "ud", "--json"], ["--robot", "127.0.0.1:502"]):
        assert_same([DEMO, *args], covered=True)


@pytest.mark.parametrize("mode", ("a", *MODES))
def test_days_long_and_impossible_times(tmp_path: Path, mode: str) -> None:
    """A capture spanning days (the automatic date of a and u), times backwards, the
    epoch, and the last second pcap holds, in every mode."""
    stream = adus(every_function_pair()[:8])
    times = [T0 + 86400 * 2.5 * i for i in range(len(stream) + 7)]
    times[5] = T0 - 3600.0  # backwards
    times[9] = 0.0  # the epoch
    times[12] = 4294967295.999999  # the last second pcap holds
    path = write_conversation(tmp_path / "days.pcap", stream, times=times)
    for fmt in ([], ["--json"]):
        assert_same([path, "-t", mode, *fmt], covered=True)


def _two_clients(path: Path) -> Path:
    """Two clients of one server, then a second server of the first client: the robot's
    labels name the peer from the second one on."""
    pairs = every_function_pair()[:6]
    convs = [
        TcpConversation("10.0.0.1:40000", "10.0.0.2:502"),
        TcpConversation("10.0.0.3:40001", "10.0.0.2:502"),
        TcpConversation("10.0.0.1:40002", "10.0.0.9:502"),
    ]
    frames: list[bytes] = list(convs[0].open())
    for c, data in adus(pairs[:2]):
        frames.append(convs[0].send(c, data))
    frames += convs[1].open()
    frames += convs[2].open()
    for c, data in adus(pairs):
        frames += [conv.send(c, data) for conv in convs]
    for conv in convs:
        frames += conv.close(True)
    return write_frames(path, [(T0 + i * 0.01, f) for i, f in enumerate(frames)])


@pytest.mark.parametrize(
    "robot", ["10.0.0.2", "10.0.0.2:502", "10.0.0.1", "10.0.0.1:40002", "10.0.0.7", "[10.0.0.2]"]
)
def test_robot_labels_with_several_peers(tmp_path: Path, robot: str) -> None:
    """The robot as server of two clients, as client of two servers, on one stream of
    several, and absent (the warning): lines, JSON lines, events and the summary."""
    path = _two_clients(tmp_path / "peers.pcap")
    for fmt in ([], ["--json"]):
        run = assert_same([path, "--robot", robot, *fmt], covered=True)
    if robot == "10.0.0.7":
        assert "appears in no stream" in run.err
    elif robot == "10.0.0.2":
        text = read_run([path, "--robot", robot]).out.decode()
        assert "Receive from client  [" in text and "Receive from client 10.0.0.3:40001" in text


# ------------------------------------------------------------------ filters and -c

FILTERS = (
    ["--fc", "3"],
    ["--fc", "3,0x10", "--json"],
    ["--unit", "1", "-c", "5"],
    ["--address", "0-10", "-t", "r"],
    ["--grep", "read", "-c", "4", "--json"],
    ["--grep", "CONNECT"],
    ["-c", "3"],
    ["--since", "+0.5s", "--until", "+3s", "-c", "6", "-t", "r"],
    ["-q", "-c", "7"],
    ["-q", "--fc", "4", "--since", "+0.2s", "-c", "2"],
)


@pytest.mark.parametrize("path", OWN + PUBLIC, ids=lambda p: p.name)
def test_filters_and_count_on_captures(path: Path) -> None:
    """Each capture under three of the filter and ``-c`` combinations (text, JSON, -q):
    the lines shown, where ``-c`` stops, and the summary as of that stop."""
    i = (OWN + PUBLIC).index(path)
    for k in range(3):
        assert_same([path, *FILTERS[(3 * i + k) % len(FILTERS)]])


@pytest.mark.parametrize(
    "args",
    [
        ["--fc", "4", "-c", "3"],
        ["--grep", "write", "-c", "2", "-t", "e", "--json"],
        ["--address", "524", "--unit", "1", "-c", "2"],
        ["-c", "2", "--since", "+0.2s", "-t", "r"],
        ["--until", "+0.01s", "--json"],
        ["--grep", "no such text"],
        ["-q", "--grep", "Write", "-c", "1"],
    ],
)
def test_the_core_covers_filters_and_count(args: list[str]) -> None:
    """Filters and ``-c`` no longer keep a covered capture off the core."""
    assert_same([DEMO, *args], covered=True)


def test_count_stops_where_the_reference_stops() -> None:
    """``-c`` counts frames the filters let through (the Connect does not count) and the
    summary is the summary of what came before the stop."""
    run = assert_same([DEMO, "-c", "3"], covered=True)
    assert len(run.out.splitlines()) == 4
    assert run.err.startswith("3 frames (2 requests, 1 answered")
    run = assert_same([DEMO, "--fc", "16", "-c", "2"], covered=True)
    lines = run.out.decode().splitlines()
    assert len(lines) == 2 and all("[u1 t" in line and "  10 " in line for line in lines)


@pytest.mark.parametrize(
    "args",
    [
        ["--where", "fc 4"],
        ["--where", "exception or latency > 5ms", "--json"],
        ["--where", "R200 != 0", "-c", "3"],
        ["--where", "connect or disconnect"],
        ["--where", "not request", "--grep", "ms"],
        ["--where", "timeout", "-q", "-c", "1"],
        ["--where", "unit 1 and address 100-200", "-t", "r"],
    ],
    ids=" ".join,
)
def test_where(tmp_path: Path, args: list[str]) -> None:
    """``--where`` (the display filter's expressions) on the core: every frame goes the
    reference's way (its Record, formatted by mbmon.format) for the expression to read,
    with and without a profile."""
    from test_core_profile import hrss_session_steps, write_capture

    session = write_capture(tmp_path / "session.pcap", hrss_session_steps())
    assert_same([DEMO, *args], covered=True)
    assert_same([ROOT / "captures" / "sim_exceptions.pcap", *args], covered=True)
    assert_same([session, "--profile", "hrss", *args], covered=True)


LOGGED = (
    ["--fc", "4"],
    ["--where", "exception or fc 16", "-c", "3"],
    ["-c", "5"],
    ["--fc", "3", "-c", "3", "--json"],
    ["--grep", "read", "-c", "4"],
    ["--grep", "connect"],
    ["-q", "-c", "9"],
    ["-q", "--fc", "4", "-c", "2"],
    ["--since", "+1s", "--until", "+2s", "-t", "r"],
)


@pytest.mark.parametrize("args", LOGGED, ids=" ".join)
def test_filters_and_count_with_a_log(tmp_path: Path, args: list[str]) -> None:
    """``-w x.mcap`` with the filters and ``-c``: the log keeps every record (it is not
    behind the filters) up to ``-c``'s last frame, as the reference's log does; the
    console shows what the filters let through."""
    from mcap_diff import log_contents

    paths = [DEMO, ROOT / "captures" / "sim_functions.pcap", *PUBLIC[9:10]]
    for path in paths:
        got, want = tmp_path / "core.mcap", tmp_path / "ref.mcap"
        fast = read_run([path, *args, "-w", got])
        pure = read_run([path, *args, "-w", want], pure=True)
        if path in (DEMO,):
            assert ran_core(fast), fast.core
        assert (fast.out, fast.err, fast.status) == (pure.out, pure.err, pure.status), path
        got_c, want_c = log_contents(got), log_contents(want)
        for i, (x, y) in enumerate(zip(got_c["messages"], want_c["messages"], strict=False)):
            assert x == y, f"{path}: message {i}"
        assert got_c == want_c, path


# ------------------------------------------------------------------ drawn combinations

_PAIRS = every_function_pair()


@st.composite
def _capture_and_options(draw: st.DrawFn) -> tuple[dict[str, object], list[str]]:
    """A generated conversation (function codes, units, times, handshake, end) and a
    command line of view options, filters and ``-c`` drawn for it."""
    picks = draw(st.lists(st.integers(0, len(_PAIRS) - 1), min_size=1, max_size=12))
    units = draw(st.lists(st.sampled_from([1, 2, 255]), min_size=len(picks), max_size=len(picks)))
    unanswered = draw(st.sets(st.integers(0, len(picks) - 1), max_size=3))
    gaps = draw(st.lists(st.sampled_from([0.001, 0.4, 2.5, 90000.0]), min_size=1, max_size=4))
    shape = {
        "picks": picks,
        "units": units,
        "unanswered": sorted(unanswered),
        "gaps": gaps,
        "handshake": draw(st.booleans()),
        "close": draw(st.sampled_from(["fin", "rst", None])),
    }
    args: list[str] = []
    if draw(st.booleans()):
        args += ["-t", draw(st.sampled_from(MODES))]
    if draw(st.booleans()):
        args.append("--json")
    if draw(st.integers(0, 4)) == 0:
        args.append("-q")
    if draw(st.booleans()):
        args += ["--fc", ",".join(map(str, draw(st.sets(st.sampled_from([1, 3, 4, 6, 16, 43, 0x41]),
                                                          min_size=1, max_size=3))))]  # fmt: skip
    if draw(st.integers(0, 3)) == 0:
        args += ["--unit", str(draw(st.sampled_from([1, 2, 255])))]
    if draw(st.integers(0, 3)) == 0:
        lo = draw(st.integers(0, 210))
        args += ["--address", f"{lo}-{lo + draw(st.integers(0, 30))}"]
    if draw(st.integers(0, 3)) == 0:
        args += ["--grep", draw(st.sampled_from(["read", "No response", "ms)", "→", "Exception",
                                                 "connect", "[u2", "zzz"]))]  # fmt: skip
    if draw(st.integers(0, 3)) == 0:
        args += ["--since", draw(st.sampled_from(["+0s", "+0.002s", "+1s", "+3s"]))]
    if draw(st.integers(0, 3)) == 0:
        args += ["--until", draw(st.sampled_from(["+0s", "+0.01s", "+2s", "+1d"]))]
    if draw(st.integers(0, 5)) == 0:
        args += ["--where", draw(st.sampled_from(["exception", "fc 3 or timeout", "not request",
                                                  "latency > 1ms", "R101 != 1"]))]  # fmt: skip
    if draw(st.booleans()):
        args += ["-c", str(draw(st.integers(1, 8)))]
    if draw(st.integers(0, 3)) == 0:
        args += ["--robot", draw(st.sampled_from(["10.0.0.2", "10.0.0.1:40000", "10.0.0.9"]))]
    return shape, args


def _write_shape(path: Path, shape: dict[str, object]) -> Path:
    from mbmon.protocol.mbap import encode_adu

    stream: list[tuple[bool, bytes]] = []
    for tid, (pick, unit) in enumerate(zip(shape["picks"], shape["units"], strict=True), 1):  # type: ignore[call-overload]
        request, answer = _PAIRS[pick]
        stream.append((True, encode_adu(tid, unit, request)))
        if tid - 1 not in shape["unanswered"]:  # type: ignore[operator]
            stream.append((False, encode_adu(tid, unit, answer)))
    gaps: list[float] = shape["gaps"]  # type: ignore[assignment]
    count = len(stream) + 7
    times, t = [], T0
    for i in range(count):
        times.append(t)
        t += gaps[i % len(gaps)]
    return write_conversation(
        path,
        stream,
        handshake=bool(shape["handshake"]),
        close=shape["close"],
        times=times,  # type: ignore[arg-type]
    )


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_capture_and_options())
def test_drawn_options_on_generated_captures(drawn: tuple[dict[str, object], list[str]]) -> None:
    """Random conversations under random combinations of ``-t``, ``--json``, ``-q``,
    ``--robot``, the filters and ``-c``: the core's bytes are the reference's."""
    shape, args = drawn
    with tempfile.TemporaryDirectory() as tmp:
        path = _write_shape(Path(tmp) / "drawn.pcap", shape)
        assert_same([path, *args])


# ------------------------------------------------------------------ with --profile

PROFILED = (
    ["--fc", "4"],
    ["--fc", "3,16", "--json"],
    ["--grep", "R200"],
    ["--grep", "°", "--json"],
    ["-c", "30"],
    ["--fc", "16", "-c", "3", "--json"],
    ["--grep", "success", "-c", "1"],
    ["--address", "200-251", "-t", "r"],
    ["--since", "+1s", "--until", "+3s"],
    ["-q", "-c", "40"],
    ["--unit", "1", "--grep", "command", "--json", "-c", "5"],
    ["--grep", "written", "--robot", "10.0.0.2"],
)


@pytest.mark.parametrize("args", PROFILED, ids=" ".join)
def test_filters_and_count_with_a_profile(tmp_path: Path, args: list[str]) -> None:
    """``--profile hrss`` with the filters and ``-c``: the lines the core notes itself
    (their notes JSON-escaped in JSON lines: what ``--grep`` reads), the annotator's,
    and the command records (asked about alone when their frame is not shown; cut
    with everything else after ``-c``'s last frame, the summary's commands too)."""
    from test_core_profile import hrss_session_steps, write_capture

    session = write_capture(tmp_path / "session.pcap", hrss_session_steps())
    for path in (session, ROOT / "captures" / "hrss_ptp.pcap"):
        assert_same([path, "--profile", "hrss", *args], covered=True)
