"""Where a device with state goes: a data-only profile that names a session plug-in.

The toy pump (:mod:`toy_pump`, a test module, not shipped) is a profile written
to a temporary file plus a session class the test registers under the name the
profile gives (``session = "toy_pump"``). Through ``mbmon read`` of a generated
capture its notes and command steps print like HRSS's; the live monitor shows
its panel; the pipeline's ticks reach it; an installed package can name it by
entry point. A data-only profile (no session) annotates the same capture with
its field notes alone, and a profile naming a session nobody registered is
refused with the file, line and the sessions known.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from toy_pump import DATA_ONLY, PROFILE, TIMEOUT, ToyPumpSession

from mbmon.format import View
from mbmon.hub import Hub
from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.model import Chunk, Direction, Phase, RecordKind, Stream, Transport
from mbmon.monitor.feed import MonitorFeed
from mbmon.pipeline import Pipeline
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response, encode_write_single
from mbmon.semantics.annotate import annotator_for
from mbmon.semantics.hrss import HrssSession
from mbmon.semantics.profile import ProfileError, load_profile
from mbmon.semantics.session import (
    Panel,
    Session,
    UnknownSession,
    is_session,
    register_session,
    session_factory,
    session_names,
    unregister_session,
)

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
T0 = 1_700_000_000.0

#: (request, answer) PDUs of the capture: set 250 ml, start, poll twice (100, then
#: 250: done), start again, then nothing for 10 s, then a read of R0..R1
EXCHANGES = [
    (encode_write_single(6, 0, 250), encode_write_single(6, 0, 250)),
    (encode_write_single(6, 1, 1), encode_write_single(6, 1, 1)),
    (encode_read_request(4, 0, 1), encode_read_response(4, [100])),
    (encode_read_request(4, 0, 1), encode_read_response(4, [250])),
    (encode_write_single(6, 1, 1), encode_write_single(6, 1, 1)),
    (encode_read_request(3, 0, 2), encode_read_response(3, [250, 1])),
]


@pytest.fixture
def toy() -> Iterator[type[Session]]:
    assert "toy_pump" not in session_names(), "no shipped session is the toy"
    register_session("toy_pump", ToyPumpSession)
    try:
        yield ToyPumpSession
    finally:
        unregister_session("toy_pump")


def _capture(path: Path) -> Path:
    """One connection carrying :data:`EXCHANGES`, 10 ms apart, the last 10 s later."""
    conv = TcpConversation("10.0.0.10:50000", "10.0.0.2:502")
    with PcapWriter(path) as out:
        for frame in conv.open():
            out.write(T0, frame)
        for tid, (req, resp) in enumerate(EXCHANGES, 1):
            ts = T0 + 0.02 * tid + (10.0 if tid == len(EXCHANGES) else 0.0)
            out.write(ts, conv.send(True, encode_adu(tid, 1, req)))
            out.write(ts + 0.01, conv.send(False, encode_adu(tid, 1, resp)))
        for frame in conv.close():
            out.write(T0 + 10.5, frame)
    return path


def _read(capture: Path, profile: Path, *, register: bool) -> subprocess.CompletedProcess[str]:
    """``mbmon read -t r --profile PROFILE CAPTURE`` in a child that registers the toy
    session first (or not)."""
    setup = (
        f"sys.path.insert(0, {str(HERE)!r}); from toy_pump import ToyPumpSession; "
        "from mbmon.semantics.session import register_session; "
        "register_session('toy_pump', ToyPumpSession); "
        if register
        else ""
    )
    code = f"import sys; {setup}from mbmon.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", code, "read", "-t", "r", "--profile", str(profile), str(capture)],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=REPO,
    )


def _lines(done: subprocess.CompletedProcess[str]) -> list[str]:
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


def test_mbmon_read_runs_a_registered_session(tmp_path: Path) -> None:
    capture = _capture(tmp_path / "pump.pcap")
    profile = tmp_path / "pump.toml"
    profile.write_text(PROFILE)
    done = _read(capture, profile, register=True)
    lines = _lines(done)
    text = "\n".join(lines)
    # the profile's field notes and the session's own note on the same line
    write = "06 00 01 00 01  | Write Single Register 1 = 1; start = start (1)"
    assert f"{write}; toy: dosing 250 ml" in text
    # the session's command steps, as COMMAND records at their frames' times
    steps = [line.split("  ", 1)[1] for line in lines if "  >> " in line]
    assert steps == [
        ">> [executing] unit 1: DOSE 250 ml",
        ">> [success after 0.050 s] unit 1: DOSE 250 ml",
        ">> [executing] unit 1: DOSE 250 ml",
        ">> [warning] unit 1: DOSE 250 ml: never completed",
    ]
    assert "robot commands: 2 (1 success, 1 executing, no status); 1 warning" in done.stderr


def test_a_data_only_profile_annotates_without_a_session(tmp_path: Path) -> None:
    capture = _capture(tmp_path / "pump.pcap")
    profile = tmp_path / "map.toml"
    profile.write_text(DATA_ONLY)
    assert load_profile(profile).session is None
    lines = _lines(_read(capture, profile, register=False))
    text = "\n".join(lines)
    assert "06 00 01 00 01  | Write Single Register 1 = 1; start = start (1)\n" in text + "\n"
    assert "04 02 00 FA  | Read Input Registers 0 = 250; dosed = 250 ml" in text
    assert "setpoint = 250 ml; start = start (1)" in text
    assert ">>" not in text and "toy:" not in text and "robot commands" not in text


def test_a_session_nobody_registered_is_refused_with_where_and_what(tmp_path: Path) -> None:
    capture = _capture(tmp_path / "pump.pcap")
    profile = tmp_path / "pump.toml"
    profile.write_text(PROFILE)
    done = _read(capture, profile, register=False)
    assert done.returncode == 2 and done.stdout == ""
    assert f"{profile}:4: profile \"session\": unknown session 'toy_pump' (known: hrss)" in (
        done.stderr
    )
    assert "Traceback" not in done.stderr
    with pytest.raises(ProfileError, match="unknown session 'toy_pump'") as err:
        load_profile(profile)
    assert (err.value.line, err.value.key) == (4, "profile.session")


def _items() -> list[Chunk]:
    stream = Stream(1, Transport.TCP, "10.0.0.10:50000", "10.0.0.2:502")
    items = []
    for tid, (req, resp) in enumerate(EXCHANGES[:5], 1):
        ts = T0 + 0.02 * tid
        items.append(Chunk(ts, stream, Direction.C2S, encode_adu(tid, 1, req)))
        items.append(Chunk(ts + 0.01, stream, Direction.S2C, encode_adu(tid, 1, resp)))
    return items


def test_the_live_monitor_shows_the_sessions_panel(toy: type[Session], tmp_path: Path) -> None:
    profile = tmp_path / "pump.toml"
    profile.write_text(PROFILE)
    annotator = annotator_for([str(profile)])
    assert annotator is not None
    feed = MonitorFeed(View(), annotator=annotator, profile=True)
    hub = Hub(Pipeline(annotator), [feed])
    items = _items()
    hub.feed(items[0])  # the setpoint written, not answered yet
    hub.tick(items[0].ts + 0.001)
    snap = feed.snapshot()
    assert (snap.panel_title, snap.parameters) == ("pump", [("R0", "setpoint", "250 ml", False)])
    for item in items[1:]:
        hub.feed(item)
    hub.tick(hub.now + 0.001)
    snap = feed.snapshot()
    assert snap.parameters == [("R0", "setpoint", "250 ml", True)]
    assert snap.state == {"dosed": 250.0}
    assert snap.command is not None and snap.command.phase is Phase.EXECUTING
    [session] = annotator.sessions().values()
    assert isinstance(session, ToyPumpSession)


def test_the_pipelines_ticks_reach_the_session_on_time(toy: type[Session], tmp_path: Path) -> None:
    profile = tmp_path / "pump.toml"
    profile.write_text(PROFILE)
    pipeline = Pipeline(annotator_for([str(profile)]))
    for item in _items():
        pipeline.feed(item)
    started = T0 + 0.02 * 5  # the second R1 = 1
    assert pipeline.next_deadline() == pytest.approx(started + TIMEOUT)
    assert [r for r in pipeline.tick(started + TIMEOUT - 0.5) if r.kind is RecordKind.COMMAND] == []
    [warning] = [r for r in pipeline.tick(started + TIMEOUT) if r.kind is RecordKind.COMMAND]
    assert warning.command is not None
    assert (warning.command.phase, warning.command.text) == (
        Phase.WARNING,
        "DOSE 250 ml: never completed",
    )
    assert pipeline.next_deadline() is None


def test_an_installed_package_names_its_session_by_entry_point(tmp_path: Path) -> None:
    """A package on the path that declares ``toy_pump`` in the ``mbmon.sessions``
    entry-point group is found by a plain ``mbmon read``, no registration in code."""
    site = tmp_path / "site"
    dist = site / "toy_pump_plugin-1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-pump-plugin\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[mbmon.sessions]\ntoy_pump = toy_pump:ToyPumpSession\n")
    capture = _capture(tmp_path / "pump.pcap")
    profile = tmp_path / "pump.toml"
    profile.write_text(PROFILE)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), str(HERE), str(REPO)]))
    done = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", "-t", "r", "--profile", str(profile), str(capture)],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=REPO,
        env=env,
    )
    assert "toy: dosing 250 ml" in "\n".join(_lines(done))


def test_the_registry(toy: type[Session]) -> None:
    assert session_factory("hrss") is HrssSession  # built in, imported when asked for
    assert session_factory("toy_pump") is ToyPumpSession
    assert {"hrss", "toy_pump"} <= set(session_names())
    assert is_session("hrss") and is_session("toy_pump") and not is_session("plc")
    with pytest.raises(UnknownSession, match=r"unknown session 'plc' \(known: hrss, toy_pump"):
        session_factory("plc")
    register_session("broken", "no_such_module_here:Session")
    try:
        with pytest.raises(UnknownSession, match="session 'broken': cannot import"):
            session_factory("broken")
    finally:
        unregister_session("broken")
    register_session("hrss", ToyPumpSession)  # replaced, then the built-in comes back
    assert session_factory("hrss") is ToyPumpSession
    unregister_session("hrss")
    assert session_factory("hrss") is HrssSession
    with pytest.raises(ValueError, match="non-empty string"):
        register_session("", ToyPumpSession)


def test_the_defaults_of_a_session() -> None:
    stream = Stream(1, Transport.TCP, "10.0.0.10:50000", "10.0.0.2:502")
    s = Session(stream, 3)
    assert (s.stream, s.unit) == (stream, 3)
    assert s.wants_read_request(1.0) and s.tick(1.0) == [] and s.next_deadline() is None
    assert s.panel() is None
    assert HrssSession(stream, 1).panel() == Panel("command registers R200..R251 as written")


def test_an_annotator_says_whether_a_profile_has_a_session(
    toy: type[Session], tmp_path: Path
) -> None:
    with_session, data_only = tmp_path / "pump.toml", tmp_path / "map.toml"
    with_session.write_text(PROFILE)
    data_only.write_text(DATA_ONLY)
    assert annotator_for([str(with_session)]).has_sessions  # type: ignore[union-attr]
    assert not annotator_for([str(data_only), "xeg"]).has_sessions  # type: ignore[union-attr]
    assert annotator_for(["unit:3=hrss", str(data_only)]).has_sessions  # type: ignore[union-attr]
