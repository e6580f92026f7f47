"""``mbmon demo`` end to end, as a process: the run, its log read back, --keep-running.

The log is read with the ``mcap`` package's own reader (not mbmon's), so a
wrong writer and a wrong demo both fail. The expected requests are written out
here from the manual (§5.4.5.2 program, Table 46 PTP parameters, Examples 4, 7,
8, 5), not taken from the program runner.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
CAPTURES = ROOT / "captures"

# Table 46: PTP {A1 90, A2..A6 0} Vel=50% Acc=100% TOOL[1] BASE[2], R201..R226
TABLE_46 = [0, 0, 24464, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 50, 100, 1, 2, 0, 0, 0, 0, 0, 0, 0, 0]
# Example 4 / Table 47: LIN {X -300, Y 300, Z 400, A 180, B 0, C 90} Vel=1000mm/s TOOL[3] BASE[7]
LIN = [1, 1, 27680, 65531, 37856, 4, 6784, 6, 48928, 2, 0, 0, 24464, 1, 1000, 100, 3, 7]
# Example 7 / Table 50: $PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0}
SET_PR = [100, 2, 2, 24464, 1] + [0] * 10


def mbmon(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mbmon", *args],
        capture_output=True,
        text=True,
        env=ENV,
        cwd=cwd,
        timeout=120,
    )


def read_log(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Every message of an MCAP log by topic, with the mcap reader, decoded by its
    channel's encoding (log format 3's /modbus/frames and /modbus/raw are protobuf)."""
    from mcap.reader import make_reader

    from mbmon.io.mcap.proto import decode_payload

    topics: dict[str, list[dict[str, Any]]] = defaultdict(list)
    with path.open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            name = schema.name if schema is not None else ""
            topics[channel.topic].append(
                decode_payload(name, channel.message_encoding, message.data)
            )
    return topics


@pytest.fixture(scope="module")
def demo_run(
    tmp_path_factory: pytest.TempPathFactory,
) -> tuple[subprocess.CompletedProcess[str], float, Path]:
    """The demo as a user runs it (paced, not --fast), plain output, timed."""
    where = tmp_path_factory.mktemp("demo")
    started = time.monotonic()
    out = mbmon("demo", "--plain", "-w", "run.mcap", cwd=where)
    return out, time.monotonic() - started, where / "run.mcap"


def test_demo_runs_under_30_seconds_and_says_what_next(
    demo_run: tuple[subprocess.CompletedProcess[str], float, Path],
) -> None:
    out, seconds, log = demo_run
    assert out.returncode == 0, out.stderr
    assert seconds < 30, f"the demo took {seconds:.1f} s"
    assert log.stat().st_size > 0
    assert out.stderr == ""
    text = out.stdout
    assert "mbmon replay run.mcap" in text
    assert "mbmon info run.mcap" in text
    assert "mbmon replay run.mcap --serve" in text
    assert "Foxglove" in text
    # the closing summary states the outcomes
    assert re.search(r"PTP \{A1 90\}: status 1, A1 = 90°", text)
    assert "LIN status 1, X Y Z = -300 300 400" in text
    assert "Set PR 1, Get PR 1 (1 = success)" in text
    assert "refused by the guard (exception 01)" in text


def test_demo_log_holds_every_step_s_frames(
    demo_run: tuple[subprocess.CompletedProcess[str], float, Path],
) -> None:
    _, _, log = demo_run
    frames = read_log(log)["/modbus/frames"]
    requests = [f for f in frames if f["kind"] == "request"]
    answers = {f["request_index"]: f for f in frames if f["kind"] != "request"}
    assert len(answers) == len(requests), "every request answered"
    assert {f["unit"] for f in frames} == {1}
    # one client connection through the proxy to the robot; what the proxy answered
    # itself (the guard's refusal) is on the proxy's own stream, client -> proxy
    robot = {f["src"] for f in frames if f["kind"] == "response"}
    assert len(robot) == 1
    to_robot = {f["stream"] for f in frames if robot & {f["src"], f["dst"]}}
    assert len(to_robot) == 1

    def find(fc: int, address: int, values: list[int] | None = None) -> list[dict[str, Any]]:
        return [
            r for r in requests
            if r["fc"] == fc and r["address"] == address
            and (values is None or r["values"][: len(values)] == values)
        ]  # fmt: skip

    # §5.4.5.2, in order: speed, set speed, DI, DO, R200 = 0, PTP parameters, R200 = 1, polls
    order = [
        find(4, 100)[0],
        find(16, 100, [90])[0],
        find(2, 300)[0],
        find(15, 300)[0],
        find(16, 200, [0])[0],
        find(16, 201, TABLE_46)[0],
        find(16, 200, [1])[0],
    ]
    assert [r["index"] for r in order] == sorted(r["index"] for r in order)
    assert answers[find(4, 100)[0]["index"]]["values"] == [100]
    assert find(2, 300)[0]["count"] == 8
    assert answers[find(2, 300)[0]["index"]]["values"] == [1, 0, 1, 0, 0, 0, 0, 0]
    assert find(15, 300)[0]["values"] == [1, 1, 0, 0, 1]
    assert find(16, 201, TABLE_46)[0]["values"] == TABLE_46
    polls = [answers[r["index"]]["values"] for r in find(4, 524)]
    assert [2] in polls and polls[-1] == [1]  # Running, then Idle
    # the extras: LIN, Set PR, Get PR, JOG, each executed by R200 = 1
    assert find(16, 201, LIN)
    assert find(16, 201, SET_PR)
    assert find(16, 201, [200, 2])
    assert find(16, 201, [3, 0, 1])
    assert len(find(16, 200, [1])) == 5
    get_pr = find(4, 200)
    got = [answers[r["index"]]["values"] for r in get_pr if r["count"] == 16]
    assert got == [[1, 200, 2, 2, 24464, 1] + [0] * 10]  # IR200..IR215: success, PR[2]
    # the guarded write: SI1 Start = ON, answered exception 01 by the proxy
    (refused,) = find(5, 0)
    answer = answers[refused["index"]]
    assert (answer["kind"], answer["exception_code"], answer["pdu"]) == ("exception", 1, "85 01")


def test_demo_log_holds_commands_their_outcomes_and_the_state(
    demo_run: tuple[subprocess.CompletedProcess[str], float, Path],
) -> None:
    _, _, log = demo_run
    topics = read_log(log)
    phases: dict[str, list[str]] = defaultdict(list)
    for message in topics["/hrss/commands"]:
        command = message["command"]
        phases[command["params"]["command"]].append(command["phase"])
    assert phases["PTP"] == ["written", "executing", "success"]
    assert phases["LIN"] == ["written", "executing", "success"]
    assert phases["Set PR"] == ["written", "executing", "success"]
    assert phases["Get PR"] == ["written", "executing", "success", "returned"]
    assert phases["JOG"] == ["written", "executing", "success"]
    commands = [m["command"] for m in topics["/hrss/commands"]]
    returned = [c for c in commands if c["phase"] == "returned"]
    assert returned[0]["text"] == "PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0}"
    a1 = [s["a1"] for s in topics["/hrss/state"] if "a1" in s]
    assert 90.0 in a1  # the PTP's target, read after the motion
    assert max(a1) > 90.0  # JOG A1 + moved on from there
    pose = [(s["x"], s["y"], s["z"], s["a"], s["b"], s["c"]) for s in topics["/hrss/state"]
            if "x" in s]  # fmt: skip
    assert pose[-1] == (-300, 300, 400, 180, 0, 90)  # where the LIN (Example 4) ended
    # the live monitor's lines (foxglove.Log) carry the robot's labels: the sim is the robot
    lines = [m["message"] for m in topics["/modbus/monitor"]]
    assert any("Receive from client" in line for line in lines)
    assert any("Send to client" in line for line in lines)


def test_demo_log_audits_the_refused_write(
    demo_run: tuple[subprocess.CompletedProcess[str], float, Path],
) -> None:
    _, _, log = demo_run
    events = read_log(log)["/mbmon/events"]
    guard = [e for e in events if e.get("event") == "guard"]
    assert len(guard) == 1
    info = guard[0]["info"]
    assert (info["rule"], info["fc"], info["address"], info["exception"]) == (
        "deny-write coil:0-255", 5, 0, 1)  # fmt: skip
    notices = [e["info"]["message"] for e in events if e.get("event") == "notice"]
    parts = [n.split(":")[0].split(" {")[0] for n in notices if n.startswith("demo")]
    assert parts == [
        "demo §5.4.5.2", "demo", "demo LIN", "demo Set PR", "demo Get PR[2] (command 200)",
        "demo JOG A1 +", "demo guard",
    ]  # fmt: skip
    # each part is told before its first request: in time, the next request is its R200 = 0
    frames = read_log(log)["/modbus/frames"]
    requests = sorted(
        (f["time"], f["fc"], f["address"], (f.get("values") or [None])[:1])
        for f in frames
        if f["kind"] == "request"
    )
    parts = ("demo LIN", "demo Set PR", "demo Get PR", "demo JOG")
    for e in events:
        message = (e.get("info") or {}).get("message", "")
        if e.get("event") == "notice" and message.startswith(parts):
            after = [r for r in requests if r[0] > e["time"]]
            assert after and after[0][1:] == (16, 200, [0]), (message, after[:1])
    kinds = [e.get("event") for e in events]
    assert kinds.count("connect") == 1 and kinds.count("disconnect") == 1
    # the client closed its connection itself before the proxy stopped
    (bye,) = [e for e in events if e.get("event") == "disconnect"]
    assert bye["info"] == {"how": "fin", "by": "client"}


def test_demo_log_reads_back_with_mbmon(
    demo_run: tuple[subprocess.CompletedProcess[str], float, Path],
) -> None:
    _, _, log = demo_run
    info = mbmon("info", str(log))
    assert info.returncode == 0, info.stderr
    assert "source:      mbmon demo" in info.stdout
    assert "guard 1" in info.stdout
    replay = mbmon("replay", str(log), "--grep", "Guard")
    assert replay.returncode == 0
    assert "refused 0x05 write coil 0 on unit 1" in replay.stdout


def test_the_demo_log_serves_the_recorded_robot_to_the_same_program(
    demo_run: tuple[subprocess.CompletedProcess[str], float, Path],
) -> None:
    """``replay --serve`` of the demo's log stands in for the sim: the §5.4.5.2 program
    (with LIN, Set/Get PR, JOG) runs to the end against it, reading what the demo read."""
    from mbmon.sim.program import run_program

    _, _, log = demo_run
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "replay", str(log), "--serve", "127.0.0.1:0"],
        env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stderr is not None
        first = proc.stderr.readline()
        m = re.search(r"on 127\.0\.0\.1:(\d+) as the recorded server", first)
        assert m, first
        result = run_program("127.0.0.1", int(m.group(1)), poll=0.01, timeout=5.0)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert result.joints == (90, 0, 0, 0, 0, 0)
    assert result.statuses == {"LIN": 1, "Set PR": 1, "Get PR": 1, "JOG": 1}
    assert result.pr2[:4] == (2, 2, 24464, 1)
    assert result.jog_moved > 1.0 and result.jog_after_stop == 0  # A1 as the demo read it
    assert ", 0 not (exception 02)" in err


def test_an_earlier_demo_log_is_overwritten_anything_else_is_not(
    demo_run: tuple[subprocess.CompletedProcess[str], float, Path], tmp_path: Path
) -> None:
    from mbmon.commands.demo import is_demo_log

    _, _, log = demo_run
    assert is_demo_log(log)
    other_log = tmp_path / "cell.mcap"  # an mbmon log, but not a demo's
    made = mbmon("read", str(CAPTURES / "hrss_ptp.pcap"), "-q", "-w", str(other_log))
    assert made.returncode == 0, made.stderr
    assert not is_demo_log(other_log)
    stranger = tmp_path / "notes.mcap"
    stranger.write_text("my notes\n")
    for path in (other_log, stranger):
        before = path.read_bytes()
        out = mbmon("demo", "--fast", "-w", str(path))
        assert out.returncode == 2
        assert "refusing to overwrite" in out.stderr
        assert path.read_bytes() == before
    out = mbmon("demo", "--fast", "-w", str(tmp_path / "demo.csv"))
    assert out.returncode == 2 and "ending in .mcap" in out.stderr
    assert not (tmp_path / "demo.csv").exists()


def test_demo_over_its_own_earlier_log(tmp_path: Path) -> None:
    first = mbmon("demo", "--fast", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    log = tmp_path / "mbmon-demo.mcap"  # the default name, in the current directory
    size = log.stat().st_size
    again = mbmon("demo", "--fast", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert len(read_log(log)["/mbmon/events"]) > 0 and log.stat().st_size > size // 2


def test_a_log_that_cannot_be_written_says_where_else_to_write_it(tmp_path: Path) -> None:
    """A folder the demo cannot write to (a read-only checkout, a missing folder) is
    one line naming the file, its reason and the way out, exit 1, before anything runs."""
    out = mbmon("demo", "--plain", "-w", str(tmp_path / "missing" / "x.mcap"))
    assert out.returncode == 1
    assert out.stdout == ""
    assert out.stderr.strip() == (
        f"mbmon: {tmp_path / 'missing' / 'x.mcap'}: cannot write: No such file or directory"
        " (log elsewhere: mbmon demo -w DIR/mbmon-demo.mcap)"
    )


def test_help_teaches() -> None:
    out = mbmon("demo", "--help")
    assert out.returncode == 0
    text = " ".join(out.stdout.split())
    for words in ("§5.4.5.2", "PTP {A1 90}", "--keep-running", "--plain", "mbmon replay",
                  "mbmon info", "Foxglove", "loopback", "not a robot simulator"):  # fmt: skip
        assert words in text, words
    assert "demo" in mbmon("--help").stdout


def test_keep_running_serves_sim_and_proxy_until_ctrl_c(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "demo", "--fast", "--keep-running", "-w", "k.mcap"],
        cwd=tmp_path,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        m = re.search(r"proxy 127\.0\.0\.1:(\d+) -> robot \(sim\) 127\.0\.0\.1:(\d+)", line)
        assert m, line
        proxy_port, sim_port = int(m.group(1)), int(m.group(2))
        # the robot directly: A1 where the demo left it (PTP to 90, then JOG A1 +)
        with ModbusTcpClient("127.0.0.1", port=sim_port, timeout=5, retries=0) as sim:
            rr = sim.read_input_registers(300, count=2, device_id=1)
            assert not rr.isError()
            a1 = (rr.registers[0] | rr.registers[1] << 16) / 1000
            assert a1 > 90
        # through the proxy: reads pass, the guard still refuses SI writes
        with ModbusTcpClient("127.0.0.1", port=proxy_port, timeout=5, retries=0) as client:
            rr = client.read_input_registers(100, count=1, device_id=1)
            assert not rr.isError() and rr.registers == [90]  # the demo set R100 = 90
            rr = client.write_coil(2, True, device_id=1)  # SI3 Stop
            assert rr.isError() and rr.exception_code == 1
            rr = client.write_coil(300, True, device_id=1)  # DO[1]: allowed
            assert not rr.isError()
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr
    assert "mbmon replay k.mcap" in stdout
    # the user's own traffic is in the log too: a second client connection
    topics = read_log(tmp_path / "k.mcap")
    frames = topics["/modbus/frames"]
    robot = {f["src"] for f in frames if f["kind"] == "response"}
    assert len(robot) == 1  # the proxy's own answers (guard) come from the proxy
    streams = {f["stream"] for f in frames if robot & {f["src"], f["dst"]}}
    assert len(streams) == 2
    guard = [e for e in topics["/mbmon/events"] if e.get("event") == "guard"]
    assert [g["info"]["address"] for g in guard] == [0, 2]


def test_ctrl_c_during_the_demo_closes_the_log(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "demo", "--plain", "-w", "cut.mcap"],
        cwd=tmp_path,
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        for line in proc.stdout:  # wait until the PTP is on its way
            if "R201..R226 written" in line:
                break
        proc.send_signal(signal.SIGINT)
        _, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, stderr
    assert "demo interrupted" in stderr and "Traceback" not in stderr
    topics = read_log(tmp_path / "cut.mcap")  # a finished file: the mcap reader takes it
    assert any(f["address"] == 201 for f in topics["/modbus/frames"])
    assert not any(f["fc"] == 5 for f in topics["/modbus/frames"])  # it stopped before the end


def test_the_closing_jog_line_measures_the_whole_jog_as_the_log_shows_it(
    demo_run: tuple[subprocess.CompletedProcess[str], float, Path],
) -> None:
    out, _, log = demo_run
    m = re.search(r"JOG moved A1 ([\d.]+)° \(([\d.]+) → ([\d.]+)°\)", out.stdout)
    assert m, out.stdout
    moved, start, end = map(float, m.groups())
    assert start == 90  # where the PTP left A1, before R200 = 1
    assert moved == pytest.approx(end - start, abs=0.01)
    a1 = [s["a1"] for s in read_log(log)["/hrss/state"] if "a1" in s]
    assert end == pytest.approx(a1[-1], abs=0.001) == pytest.approx(max(a1), abs=0.001)
