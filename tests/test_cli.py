"""`mbmon read` and `mbmon decode` as a user runs them: real files, real subprocesses."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response

REPO = Path(__file__).resolve().parents[1]
MBMON = [sys.executable, "-m", "mbmon"]


def run(*args: str, check: bool = False) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*MBMON, *args], capture_output=True, text=True, check=check, timeout=120)


def write_polling_pcap(path: Path, polls: int = 20) -> None:
    """A client polling holding registers 400..401, one request/response per poll."""
    conv = TcpConversation("10.0.0.1:50000", "10.0.0.2:502")
    with PcapWriter(path) as out:
        ts = 1_700_000_000.0
        for frame in conv.open():
            out.write(ts, frame)
        for tid in range(1, polls + 1):
            ts += 0.1
            out.write(ts, conv.send(True, encode_adu(tid, 1, encode_read_request(3, 400, 2))))
            out.write(
                ts + 0.002, conv.send(False, encode_adu(tid, 1, encode_read_response(3, [tid, 0])))
            )
        for frame in conv.close():
            out.write(ts + 0.01, frame)


def test_read_prints_monitor_lines(tmp_path: Path) -> None:
    cap = tmp_path / "poll.pcap"
    write_polling_pcap(cap, polls=3)
    out = run("read", str(cap), check=True).stdout.splitlines()
    assert out[0].endswith("Connect 10.0.0.1:50000 → 10.0.0.2:502 (tcp)")
    assert (
        "10.0.0.1:50000 → 10.0.0.2:502  [u1 t1]  03 01 90 00 02  | Read Holding Registers 400..401"
        in out[1]
    )
    assert "[u1 t1]  03 04 00 01 00 00  | Read Holding Registers 400..401 = 1, 0 (2.0 ms)" in out[2]
    assert "Disconnect" in out[-1]
    assert len(out) == 1 + 6 + 1


def test_read_json_pairs_requests_and_responses(tmp_path: Path) -> None:
    cap = tmp_path / "poll.pcap"
    write_polling_pcap(cap, polls=5)
    rows = [
        json.loads(line) for line in run("read", str(cap), "--json", check=True).stdout.splitlines()
    ]
    frames = [r for r in rows if r["kind"] in ("request", "response")]
    assert len(frames) == 10
    for req, resp in zip(frames[::2], frames[1::2], strict=True):
        assert resp["request_index"] == req["index"]
        assert resp["tid"] == req["tid"] and resp["address"] == 400 and resp["count"] == 2
        assert resp["latency_ms"] == pytest.approx(2.0, abs=0.01)
        assert resp["src"] == "10.0.0.2:502" and resp["transport"] == "tcp"


def test_robot_view_labels(tmp_path: Path) -> None:
    cap = tmp_path / "poll.pcap"
    write_polling_pcap(cap, polls=1)
    out = run("read", str(cap), "--robot", "10.0.0.2", check=True).stdout.splitlines()
    assert out[0].endswith("Client 10.0.0.1:50000 connected")
    assert "Receive from client  [u1 t1]  03 01 90 00 02" in out[1]
    assert "Send to client  [u1 t1]  03 04 00 01 00 00" in out[2]
    assert out[-1].endswith("Client 10.0.0.1:50000 disconnected (FIN by client)")


def test_missing_file_is_one_clear_error(tmp_path: Path) -> None:
    res = run("read", str(tmp_path / "nope.pcap"))
    assert res.returncode == 1
    assert res.stdout == ""
    assert "nope.pcap" in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_not_a_capture(tmp_path: Path) -> None:
    bad = tmp_path / "notes.pcap"
    bad.write_text("<!DOCTYPE html> this is not a capture\n" * 10)
    res = run("read", str(bad))
    assert res.returncode == 1
    assert "not a pcap" in res.stderr and "Traceback" not in res.stderr


def test_truncated_capture_keeps_everything_before_the_damage(tmp_path: Path) -> None:
    cap = tmp_path / "poll.pcap"
    write_polling_pcap(cap, polls=20)
    full = [json.loads(x) for x in run("read", str(cap), "--json", check=True).stdout.splitlines()]
    data = cap.read_bytes()
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    res = run("read", str(cut), "--json")
    assert res.returncode == 1
    assert "Traceback" not in res.stderr
    assert "truncated" in res.stderr
    got = [json.loads(x) for x in res.stdout.splitlines()]
    frames = [r["pdu"] for r in got if r["kind"] in ("request", "response")]
    full_frames = [r["pdu"] for r in full if r["kind"] in ("request", "response")]
    assert 20 <= len(frames) < len(full_frames)
    assert frames == full_frames[: len(frames)]
    assert any(r["kind"] == "event" and r["event"] == "error" for r in got)


def test_usage_errors_exit_2() -> None:
    assert run("read").returncode == 2
    res = run("read", "x.pcap", "--port", "70000")
    assert res.returncode == 2 and "port out of range" in res.stderr
    res = run("decode", "zz")
    assert res.returncode == 2 and "not hex" in res.stderr


def test_help_teaches() -> None:
    out = run("read", "--help", check=True).stdout
    assert "examples:" in out and "--robot" in out and "--rtu-raw" in out


@pytest.mark.parametrize("command", ["read", "sniff", "replay"])
def test_help_that_points_to_times_has_them(command: str) -> None:
    """--since/--until say "see 'times' below": every command with them has that section."""
    out = run(command, "--help", check=True).stdout
    assert "see 'times' below" in out
    assert "\ntimes: +5s" in out


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["02", "01", "2C", "00", "05"], "Read Discrete Inputs 300..304"),
        (["--response", "02 01 13"], "Read Discrete Inputs = 11001000"),
        (["01 03 00 00 00 0A C5 CD"], "framing: RTU ADU"),
        (["00 01 00 00 00 06 01 03 00 00 00 01"], "framing: Modbus/TCP ADU"),
        (["83", "02"], "Exception 02 Illegal Data Address"),
        (
            ["10 00 c9 00 03 06 00 6f 00 de 01 4d"],
            "Write Multiple Registers 201..203 = 111, 222, 333",
        ),
    ],
)
def test_decode(args: list[str], expected: str) -> None:
    res = run("decode", *args, check=True)
    assert expected in res.stdout


def test_decode_with_profile() -> None:
    res = run("decode", "--profile", "hrss", "06 00 C8 00 01", check=True)
    assert "R200 = 1 (execute)" in res.stdout


def test_broken_pipe_is_quiet(tmp_path: Path) -> None:
    cap = tmp_path / "poll.pcap"
    write_polling_pcap(cap, polls=3000)
    if shutil.which("head") is None:
        pytest.skip("no head(1) on this machine")
    proc = subprocess.run(
        f"{sys.executable} -m mbmon read {cap} | head -n 2",
        shell=True,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert len(proc.stdout.splitlines()) == 2
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr


def test_progress_bar_on_a_terminal_only(tmp_path: Path) -> None:
    """A long file shows a rich progress bar on stderr when stderr is a TTY, never otherwise."""
    import os
    import pty

    cap = tmp_path / "big.pcap"
    write_polling_pcap(cap, polls=30_000)  # > 4 MiB: the bar's threshold
    assert cap.stat().st_size > 4 << 20
    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [*MBMON, "read", "-q", str(cap)],
        stdout=subprocess.DEVNULL,
        stderr=slave,
        env={**os.environ, "COLUMNS": "100", "TERM": "xterm"},
    )
    os.close(slave)
    seen = b""
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        seen += data
    assert proc.wait(timeout=120) == 0
    os.close(master)
    assert b"reading big.pcap" in seen
    piped = run("read", "-q", str(cap))
    assert piped.returncode == 0 and piped.stderr == ""


def test_read_from_stdin(tmp_path: Path) -> None:
    cap = tmp_path / "poll.pcap"
    write_polling_pcap(cap, polls=4)
    res = subprocess.run(
        [*MBMON, "read", "-", "--json"],
        input=cap.read_bytes(),
        capture_output=True,
        timeout=120,
        check=True,
    )
    rows = [json.loads(x) for x in res.stdout.splitlines()]
    assert sum(r["kind"] == "response" for r in rows) == 4


@pytest.mark.parametrize("suffix", [".jsonl", ".mcap", ".txt"])
def test_full_disk_is_one_clear_error(tmp_path: Path, suffix: str) -> None:
    """Writing to a full disk (/dev/full) ends with a message and exit 1, no traceback."""
    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this machine")
    target = tmp_path / f"full{suffix}"
    target.symlink_to("/dev/full")
    res = run("read", str(REPO / "captures" / "hrss_ptp.pcap"), "-q", "-w", str(target))
    assert res.returncode == 1
    assert "No space left on device" in res.stderr and "Traceback" not in res.stderr


def test_a_pipe_streams_records_as_they_arrive(tmp_path: Path) -> None:
    """`tcpdump -w - | mbmon read -`: records come out before the writer is done."""
    import select

    cap = tmp_path / "poll.pcap"
    write_polling_pcap(cap, polls=50)
    data = cap.read_bytes()
    proc = subprocess.Popen(
        [*MBMON, "read", "-"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdin is not None and proc.stdout is not None
    try:
        proc.stdin.write(data[: len(data) // 4])
        proc.stdin.flush()
        ready, _, _ = select.select([proc.stdout], [], [], 30)
        assert ready, "no record within 30 s while the pipe stays open"
        first = proc.stdout.readline().decode()
        assert "Connect 10.0.0.1:50000" in first
        proc.stdin.write(data[len(data) // 4 :])
        proc.stdin.close()
        rest = proc.stdout.read().decode().splitlines()
        assert proc.wait(timeout=60) == 0
        assert len(rest) == 100 + 1  # 50 requests, 50 responses, the disconnect
    finally:
        proc.kill()
