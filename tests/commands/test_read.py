"""`mbmon read` as a user meets it: output under a terminal, outputs that are inputs,
a closed stdout with a log, summaries, hints, validation, stream inputs, Ctrl-C."""

from __future__ import annotations

import json
import os
import pty
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response
from mbmon.protocol.rtu import encode_rtu

REPO = Path(__file__).resolve().parents[2]
MBMON = [sys.executable, "-m", "mbmon"]
HRSS = REPO / "captures" / "hrss_ptp.pcap"


def run(*args: str, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*MBMON, *args], capture_output=True, text=True, timeout=180, cwd=REPO, **kw
    )  # type: ignore[call-overload]


def polling_pcap(
    path: Path, polls: int, *, clients: int = 1, server: str = "10.0.0.2:502", exc_every: int = 0
) -> None:
    """Clients polling a server; every ``exc_every``-th answer is an exception."""
    convs = [TcpConversation(f"10.0.0.{c + 10}:5000{c}", server) for c in range(clients)]
    with PcapWriter(path) as out:
        ts = 1_700_000_000.0
        for conv in convs:
            for frame in conv.open():
                out.write(ts, frame)
        for tid in range(1, polls + 1):
            for conv in convs:
                ts += 0.01
                out.write(ts, conv.send(True, encode_adu(tid, 1, encode_read_request(3, 0, 2))))
                if exc_every and tid % exc_every == 0:
                    answer = bytes([0x83, 0x02])
                else:
                    answer = encode_read_response(3, [tid & 0xFFFF, 0])
                out.write(ts + 0.002, conv.send(False, encode_adu(tid, 1, answer)))
        for conv in convs:
            for frame in conv.close():
                out.write(ts + 0.01, frame)


@pytest.fixture(scope="module")
def big(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Over 4 MiB: big enough for the progress bar, with exceptions to grep for."""
    path = tmp_path_factory.mktemp("big") / "big.pcap"
    polling_pcap(path, 30_000, exc_every=100)
    assert path.stat().st_size > 4 << 20
    return path


def _under_terminal_stderr(args: list[str], stdout_path: Path) -> tuple[int, bytes]:
    """Run with stderr on a real pseudo-terminal and stdout to a file."""
    master, slave = pty.openpty()
    with open(stdout_path, "wb") as out:
        proc = subprocess.Popen(
            [*MBMON, *args],
            stdout=out,
            stderr=slave,
            cwd=REPO,
            env={**os.environ, "COLUMNS": "100", "TERM": "xterm"},
        )
    os.close(slave)
    seen = b""
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:
            break
        if not data:
            break
        seen += data
    code = proc.wait(timeout=180)
    os.close(master)
    return code, seen


@pytest.mark.parametrize(
    "extra",
    [[], ["--json", "--profile", "hrss"], ["-w", "{tmp}/x.jsonl"]],
    ids=["text", "json-profile", "with-log"],
)
def test_records_go_to_stdout_not_the_terminal_of_stderr(
    big: Path, tmp_path: Path, extra: list[str]
) -> None:
    """With stderr on a terminal (the progress bar shows), every record still
    goes to the redirected stdout; the terminal gets the bar and the summary only."""
    args = ["read", str(big), *(a.format(tmp=tmp_path) for a in extra)]
    out = tmp_path / "out.txt"
    code, terminal = _under_terminal_stderr(args, out)
    assert code == 0
    lines = out.read_bytes().splitlines()
    assert len(lines) == 1 + 60_000 + 1  # connect, requests and answers, disconnect
    if "--json" in extra:
        assert sum(json.loads(line)["kind"] == "exception" for line in lines) == 300
    else:
        assert sum(b"Exception" in line for line in lines) == 300
    assert b"reading big.pcap" in terminal  # the bar was there, on the terminal
    assert b"03 00 00 00 02" not in terminal  # but no record


def test_an_output_that_is_an_input_is_refused(tmp_path: Path) -> None:
    """`read IN -w IN` (also through a symlink or a hard link) never truncates IN."""
    cap = tmp_path / "in.pcap"
    cap.write_bytes(HRSS.read_bytes())
    before = cap.read_bytes()
    (tmp_path / "link.pcap").symlink_to(cap)
    os.link(cap, tmp_path / "hard.pcap")
    for target in ("in.pcap", "link.pcap", "hard.pcap"):
        res = run("read", str(cap), "-w", str(tmp_path / target))
        assert res.returncode == 2, res.stderr
        assert "refusing to overwrite" in res.stderr and "usage: mbmon read" in res.stderr
    assert cap.read_bytes() == before
    rtu = tmp_path / "bus.bin"
    rtu.write_bytes(encode_rtu(1, encode_read_request(3, 0, 1)))
    res = run("read", "--rtu-raw", str(rtu), "-w", str(rtu))
    assert res.returncode == 2 and rtu.stat().st_size == 8


def test_a_closed_stdout_stops_printing_but_the_log_gets_everything(
    big: Path, tmp_path: Path
) -> None:
    """`read big -w x.mcap | head -1`: the log holds every record."""
    log = tmp_path / "x.mcap"
    proc = subprocess.run(
        f"{sys.executable} -m mbmon read {big} -w {log} | head -n 1",
        shell=True,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )
    assert len(proc.stdout.splitlines()) == 1
    assert "Traceback" not in proc.stderr and "Broken pipe" not in proc.stderr
    with open(log, "rb") as f:
        frames = sum(1 for _ in make_reader(f).iter_messages(topics=["/modbus/frames"]))
    assert frames == 60_000


def test_summary_on_stderr_and_q_silences_it(tmp_path: Path) -> None:
    cap = tmp_path / "poll.pcap"
    polling_pcap(cap, 50, exc_every=10)
    res = run("read", str(cap))
    assert res.returncode == 0
    assert "100 frames (50 requests, 50 answered, 5 exceptions, 0 unanswered" in res.stderr
    assert "on 1 streams" in res.stderr and "time span: " in res.stderr
    quiet = run("read", str(cap), "-q", "-w", str(tmp_path / "x.jsonl"))
    assert quiet.returncode == 0 and quiet.stderr == "" and quiet.stdout == ""
    hrss = run("read", str(HRSS), "--profile", "hrss")
    assert "robot commands: " in hrss.stderr and "success" in hrss.stderr


def test_count_stops_after_n_frames_events_do_not_count(tmp_path: Path) -> None:
    """``-c N`` counts frames (as ``sniff``'s does): the Connect event before them is
    shown but not counted."""
    cap = tmp_path / "poll.pcap"
    polling_pcap(cap, 50)
    res = run("read", str(cap), "-c", "7", "--json")
    assert res.returncode == 0
    lines = [json.loads(x) for x in res.stdout.splitlines()]
    assert [x["kind"] for x in lines] == ["event"] + ["request", "response"] * 3 + ["request"]
    assert [x["index"] for x in lines] == list(range(8))
    assert "7 frames (4 requests" in res.stderr
    assert run("read", str(cap), "-c", "0").returncode == 2


def test_count_counts_what_the_filters_let_through_and_logs_end_there(tmp_path: Path) -> None:
    """With filters, ``-c N`` counts the frames they let through; the screen shows those,
    and every ``-w`` log ends at the same (N-th counted) frame."""
    cap = tmp_path / "poll.pcap"
    polling_pcap(cap, 50, exc_every=10)
    log = tmp_path / "log.jsonl"
    res = run("read", str(cap), "-c", "2", "--grep", "exception", "--json", "-w", str(log))
    assert res.returncode == 0, res.stderr
    shown = [json.loads(x) for x in res.stdout.splitlines()]
    assert [x["exception_code"] for x in shown] == [2, 2]
    logged = [json.loads(x) for x in log.read_text().splitlines()]
    # everything up to the second exception answer (tid 20), nothing after it
    assert logged[-1]["index"] == shown[-1]["index"] and logged[-1]["tid"] == 20
    assert sum(1 for x in logged if x["kind"] != "event") == 40


def test_no_modbus_names_the_busiest_ports(tmp_path: Path) -> None:
    """A capture with Modbus on another port says where the traffic is (with
    port detection off; on, the port is found by the structure of its bytes)."""
    cap = tmp_path / "other.pcap"
    polling_pcap(cap, 20, server="10.0.0.2:1502")
    res = run("read", str(cap), "--no-detect")
    assert res.returncode == 0 and res.stdout == ""
    assert "no Modbus found on port 502" in res.stderr
    assert "tcp/1502" in res.stderr and "--port 1502" in res.stderr
    assert len(run("read", str(cap), "--port", "1502").stdout.splitlines()) == 42
    found = run("read", str(cap))
    assert len(found.stdout.splitlines()) == 42
    assert "found Modbus/TCP on port 1502 by its structure" in found.stderr


def test_an_mcap_log_suggests_replay(tmp_path: Path) -> None:
    log = tmp_path / "cell.mcap"
    assert run("read", str(HRSS), "-q", "-w", str(log)).returncode == 0
    res = run("read", str(log))
    assert res.returncode == 1
    assert f"mbmon replay {log}" in res.stderr and "Traceback" not in res.stderr


def test_robot_option_is_checked_and_a_missing_robot_is_a_warning(tmp_path: Path) -> None:
    """A malformed --robot is a usage error (exit 2); a robot that appears in no
    stream is a warning, not an error."""
    for bad in ("10.0.0.2:notaport", "10.0.0.2:70000", "a b", "[::1"):
        res = run("read", str(HRSS), "--robot", bad)
        assert res.returncode == 2, bad
        assert "usage: mbmon read" in res.stderr
    res = run("read", str(HRSS), "--robot", "192.0.2.99")
    assert res.returncode == 0
    assert "warning: the robot 192.0.2.99 (--robot) appears in no stream" in res.stderr
    assert "appears in no stream" not in run("read", str(HRSS), "--robot", "127.0.0.1:502").stderr


def test_with_several_clients_robot_labels_name_the_peer(tmp_path: Path) -> None:
    cap = tmp_path / "two.pcap"
    polling_pcap(cap, 3, clients=2)
    lines = run("read", str(cap), "--robot", "10.0.0.2").stdout.splitlines()
    frames = [line for line in lines if "[u1 t" in line]
    assert any("Receive from client 10.0.0.10:50000  [u1 t2]" in x for x in frames)
    assert any("Send to client 10.0.0.11:50001  [u1 t3]" in x for x in frames)
    one = run("read", str(HRSS), "--robot", "127.0.0.1:502").stdout
    assert "Receive from client  [" in one  # one client: the robot's own label


@pytest.mark.parametrize(
    "args",
    [
        ["--baud", "0"],
        ["--baud", "-9600"],
        ["--timeout", "0"],
        ["--timeout", "nan"],
        ["-w", "out.xyz"],
        ["--port", "70000"],
    ],
)
def test_bad_values_are_usage_errors_with_the_commands_usage(args: list[str]) -> None:
    """Exit 2 and the command's own usage, for every bad value."""
    res = run("read", str(HRSS), *args)
    assert res.returncode == 2, res
    assert "usage: mbmon read" in res.stderr and "Traceback" not in res.stderr


def test_rtu_raw_reads_a_pipe_and_a_fifo(tmp_path: Path) -> None:
    """`cat dump | mbmon read --rtu-raw -`, and a FIFO."""
    data = b"".join(
        encode_rtu(1, encode_read_request(3, i, 1)) + encode_rtu(1, encode_read_response(3, [i]))
        for i in range(10)
    )
    res = subprocess.run(
        [*MBMON, "read", "--rtu-raw", "-"], input=data, capture_output=True, timeout=60, cwd=REPO
    )
    assert res.returncode == 0 and len(res.stdout.splitlines()) == 20
    fifo = tmp_path / "bus.fifo"
    os.mkfifo(fifo)
    proc = subprocess.Popen(
        [*MBMON, "read", "--rtu-raw", str(fifo)], stdout=subprocess.PIPE, cwd=REPO
    )
    with open(fifo, "wb") as w:
        w.write(data)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0 and len(out.splitlines()) == 20


def test_ctrl_c_during_read_w_says_the_log_is_finished(tmp_path: Path) -> None:
    """Ctrl-C while recording a pipe: the log is finished, and it says where."""
    cap = tmp_path / "poll.pcap"
    polling_pcap(cap, 200)
    log = tmp_path / "live.mcap"
    proc = subprocess.Popen(
        [*MBMON, "read", "-", "-q", "-w", str(log)],
        stdin=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=REPO,
    )
    assert proc.stdin is not None and proc.stderr is not None
    proc.stdin.write(cap.read_bytes())  # the pipe stays open: a live capture
    proc.stdin.flush()
    # Ctrl-C once everything is on disk (the log flushes every second): its size has
    # settled above zero; on a loaded machine mbmon may take seconds just to start
    deadline, last, settled = time.monotonic() + 60, -1, 0.0
    while time.monotonic() < deadline:
        size = log.stat().st_size if log.exists() else 0
        if size and size == last:
            if time.monotonic() - settled >= 1.5:
                break
        else:
            last, settled = size, time.monotonic()
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    err = proc.stderr.read().decode()
    proc.wait(timeout=60)
    proc.stdin.close()
    assert proc.returncode == 130
    assert f"{log} was finished" in err and "Traceback" not in err
    with open(log, "rb") as f:
        assert sum(1 for _ in make_reader(f).iter_messages(topics=["/modbus/frames"])) == 400


def test_no_response_is_printed_at_the_request_time_plus_the_timeout(tmp_path: Path) -> None:
    # a request at t0 never answered, the next packet 15 s later, a Force Listen Only
    # request (which the spec leaves unanswered) in between: one "No response" line,
    # at t0 + 1 s (the default --timeout), before the later packet's line
    path = tmp_path / "quiet.pcap"
    conv = TcpConversation("10.0.0.10:50000", "10.0.0.2:502")
    t0 = 1_700_000_000.0
    with PcapWriter(path) as out:
        for frame in conv.open():
            out.write(t0 - 1, frame)
        out.write(t0, conv.send(True, encode_adu(1, 1, encode_read_request(3, 0, 2))))
        out.write(t0 + 0.5, conv.send(True, encode_adu(2, 1, bytes.fromhex("08 0004 0000"))))
        out.write(t0 + 15, conv.send(True, encode_adu(3, 1, encode_read_request(3, 0, 2))))
        out.write(t0 + 15.01, conv.send(False, encode_adu(3, 1, encode_read_response(3, [1, 2]))))
    proc = run("read", str(path), "--json")
    assert proc.returncode == 0, proc.stderr
    records = [json.loads(line) for line in proc.stdout.splitlines()]
    timeouts = [r for r in records if r.get("event") == "timeout"]
    assert len(timeouts) == 1, timeouts
    assert timeouts[0]["info"]["tid"] == 1
    assert timeouts[0]["time"] == pytest.approx(t0 + 1.0, abs=1e-3)
    times = [r["time"] for r in records]
    assert times == sorted(times)


def _rtu_bus() -> bytes:
    """A bus: noise, reads and writes of unit 1, the writes of R10..R14 answered."""
    from mbmon.protocol.pdu import encode_read_request, encode_read_response

    frames = [b"\x00\xff\x13"]  # noise first: it never counts
    for n in range(5):
        frames.append(encode_rtu(1, encode_read_request(3, 0, 1)))
        frames.append(encode_rtu(1, encode_read_response(3, [n])))
        write = bytes([6, 0, 10 + n, 0, n])
        frames += [encode_rtu(1, write), encode_rtu(1, write)]
    return b"".join(frames)


def _frames(stdout: str) -> list[tuple[object, ...]]:
    out = []
    for line in stdout.splitlines():
        obj = json.loads(line)
        if obj["fc"] is not None:
            out.append((obj["kind"], obj["fc"], obj["address"], obj["values"]))
    return out


def test_read_and_sniff_count_the_same_frames(tmp_path: Path) -> None:
    """One -c: the same bus through ``read --rtu-raw`` and ``sniff --serial`` (a socat pty
    pair) with ``--fc 6 -c 3``: both show the same three writes, noise and reads not
    counted, and both end there by themselves."""
    import shutil

    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (sniff --serial needs a pty pair)")
    from socat_ptys import pty_pair

    bus = tmp_path / "bus.bin"
    bus.write_bytes(_rtu_bus())
    args = ("--fc", "6", "-c", "3", "--json")
    read = run("read", "--rtu-raw", str(bus), *args)
    assert read.returncode == 0, read.stderr
    expected = [("request", 6, 10, [0]), ("response", 6, 10, [0]), ("request", 6, 11, [1])]
    assert _frames(read.stdout) == expected
    with pty_pair() as (writer, reader):
        sniff = subprocess.Popen(
            [*MBMON, "sniff", "--serial", reader, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
        )
        try:
            deadline = time.monotonic() + 60
            while sniff.poll() is None and time.monotonic() < deadline:
                with open(writer, "wb", buffering=0) as port:
                    port.write(_rtu_bus())  # again until it has seen three writes
                time.sleep(0.5)
            out, err = sniff.communicate(timeout=60)
        finally:
            if sniff.poll() is None:
                sniff.kill()
                sniff.communicate()
    assert sniff.returncode == 0, err
    assert _frames(out) == expected, out


def test_a_bad_trigger_or_a_log_that_cannot_open_leaves_no_log_half_written(
    tmp_path: Path,
) -> None:
    cap = tmp_path / "poll.pcap"
    polling_pcap(cap, 5)
    log = tmp_path / "x.mcap"
    bad = run("read", str(cap), "-w", str(log), "--trigger", "fc ((")
    assert bad.returncode == 2 and "--trigger" in bad.stderr
    assert not log.exists()  # checked before any output is opened
    first = tmp_path / "x.jsonl"
    res = run("read", str(cap), "-w", str(first), "-w", str(tmp_path / "no" / "such.jsonl"))
    assert res.returncode == 1 and "such.jsonl" in res.stderr and "Traceback" not in res.stderr
    assert first.exists() and first.read_text() == ""  # closed before anything was read
