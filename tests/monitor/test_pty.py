"""The monitor on a real pseudo-terminal, read back through a VT100 emulator (pyte):
``sniff lo`` and ``demo`` under the screen (the list is what ``read`` prints of the
same traffic; a screen paused 5 s loses nothing from ``-w x.mcap``), and
``replay --browse`` (search, filter, details, marks) on a recorded log."""

from __future__ import annotations

import json
import os
import re
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
from term import REPO, Terminal

from mbmon.sim.server import SimServer

ROOT = pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() != 0,
    reason="live capture needs root (an AF_PACKET socket); CI runs as root",
)


def _mbmon(*args: str) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-m", "mbmon", *args],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.splitlines()


def list_rows(screen: str) -> list[str]:
    """The monitor lines the list pane shows (its border and gutter taken off)."""
    rows = screen.splitlines()
    top = next(i for i, r in enumerate(rows) if r.startswith("╭─ monitor"))
    right = rows[top].index("╮")
    out = []
    for row in rows[top + 1 :]:
        if row.startswith("╰"):
            break
        text = row[3:right].rstrip(" ▁▂▃▄▅▆▇█")  # a scrollbar may sit on the right
        if re.match(r"\d\d:\d\d:\d\d\.\d{6}  ", text):
            out.append(text)
    return out


def _adu(tid: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, 1) + pdu


def _talk(port: int) -> None:
    """A client's few requests to the simulated robot, each answered before the next."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        for tid, pdu in enumerate(
            [
                bytes.fromhex("0400640001"),  # IR100
                bytes.fromhex("0600640050"),  # R100 = 80
                bytes.fromhex("0300640001"),  # R100
                bytes.fromhex("0100000008"),  # coils 0..7
            ],
            start=1,
        ):
            s.sendall(_adu(tid, pdu))
            got = b""
            while len(got) < 7 or len(got) < 6 + int.from_bytes(got[4:6]):
                part = s.recv(300)
                assert part
                got += part
            time.sleep(0.05)


@ROOT
def test_sniff_lo_list_is_what_read_prints(tmp_path: Path) -> None:
    pcap, log = tmp_path / "x.pcap", tmp_path / "x.mcap"
    with SimServer() as sim:
        args = ["sniff", "lo", "--port", str(sim.port), "-w", str(pcap), "-w", str(log)]
        term = Terminal(args, 300, 50)
        try:
            term.wait_for(lambda s: " LIVE " in s)
            time.sleep(0.5)  # the capture is open before the screen; let it settle
            _talk(sim.port)
            screen = term.wait_for(lambda s: "disconnected" in s or "Disconnect" in s)
            saved = tmp_path / "kept.jsonl"  # w while the capture runs: in the hub's thread
            term.press("w")
            term.press(f"{saved}\r", 1.0)
            term.wait_for(lambda s: "wrote " in s)
            term.press("\x03")  # ctrl+c: the key, as a user presses it
            out = term.finish()
        finally:
            term.close()
    assert term.proc.returncode == 0, out[-2000:]
    assert "mbmon: sniffed lo for" in out  # the summary, after the screen
    shown = list_rows(screen)
    assert len(shown) >= 10, screen
    assert [json.loads(x)["line"] for x in saved.read_text().splitlines()] == shown
    # exactly the lines of the run, as its log holds them (but the closing stats, which
    # come after the screen)
    logged = _mbmon("replay", str(log))
    assert "-- Stats: interface=lo" in logged[-1]
    assert shown == logged[:-1]
    # and what read prints of the capture written alongside; the pcap keeps whole
    # microseconds, so a time may print one microsecond apart
    read = _mbmon("read", str(pcap), "--port", str(sim.port))
    assert [_untimed(x) for x in shown] == [_untimed(x) for x in read]
    for a, b in zip(shown, read, strict=True):
        assert abs(_seconds(a) - _seconds(b)) <= 1.5e-6, (a, b)


def _untimed(line: str) -> str:
    return line.split("  ", 1)[1]


def _seconds(line: str) -> float:
    h, m, s = line.split("  ", 1)[0].split(":")
    return int(h) * 3600 + int(m) * 60 + float(s)


def test_demo_paused_5_s_loses_nothing(tmp_path: Path) -> None:
    log = tmp_path / "x.mcap"
    kept = tmp_path / "kept.txt"
    term = Terminal(["demo", "-w", str(log)], 200, 50, cwd=tmp_path)
    try:
        term.wait_for(lambda s: " LIVE " in s, 60)
        term.press(" ")
        paused_at = term.wait_for(lambda s: " PAUSED " in s)
        frozen = list_rows(paused_at)
        end = time.monotonic() + 5
        while time.monotonic() < end:
            term.pump(0.2)
        still = term.text()
        assert " PAUSED " in still and list_rows(still) == frozen  # the view held
        term.press(" ")
        term.wait_for(lambda s: " ENDED " in s and "demo done" in s, 90)
        term.press("w")
        term.press(str(kept) + "\r", 1.0)
        term.wait_for(lambda s: "wrote " in s)
        term.press("q")
        out = term.finish(60)
    finally:
        term.close()
    assert term.proc.returncode == 0, out[-2000:]
    m = re.search(r"mbmon demo: done in [\d.]+ s, (\d+) requests through the proxy", out)
    assert m, out[-2000:]
    logged = _mbmon("replay", str(log))
    # the kept lines (what the list holds after the pause) are the log's lines, all of them
    assert kept.read_text().splitlines() == logged
    requests = _mbmon("replay", str(log), "--json")
    assert sum('"kind":"request"' in line for line in requests) == int(m.group(1))


@pytest.fixture(scope="module")
def demo_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    where = tmp_path_factory.mktemp("demo")
    log = where / "demo.mcap"
    _mbmon("demo", "--fast", "--plain", "-w", str(log))
    return log


def test_replay_browse_search_filter_details_marks(demo_log: Path) -> None:
    lines = _mbmon("replay", str(demo_log))
    term = Terminal(["replay", "--browse", str(demo_log)], 160, 50)
    try:
        term.wait_for(lambda s: " ENDED " in s)
        term.pump(1.0)
        screen = term.text()
        assert f"monitor: {len(lines)} lines" in screen
        rows = list_rows(screen)  # the newest lines, cut at the pane's width
        newest = lines[-len(rows) :]
        assert all(line.startswith(row) for row, line in zip(rows, newest, strict=True)), newest
        # search: the guard's refusal, its details (the event) in the details pane
        term.press("/")
        term.press("refused 0x05\r", 0.8)
        screen = term.text()
        guard = next(line for line in lines if "refused 0x05" in line)
        assert "message: refused 0x05" in screen, screen
        # the frame before it: details as decode prints them, the pair and the raw bytes
        term.press("\x1b[A\x1b[A", 0.8)  # up, up: the refused write itself
        screen = term.text()
        assert "kind: request" in screen and "meaning: Write Single Coil 0 = ON" in screen
        assert "answer #" in screen and "latency:" in screen
        # marks: m here, then ' from elsewhere comes back
        term.press("m")
        term.press("\x1b[H", 0.5)  # home
        term.press("'", 0.8)
        screen = term.text()
        assert "›●" in screen and "Write Single Coil 0 = ON" in screen.split("›●", 1)[1][:200]
        # filter: only FC 16, the command-line syntax
        term.press("f")
        term.press("--fc 16\r", 1.0)
        screen = term.text()
        fc16 = _mbmon("replay", str(demo_log), "--fc", "16")
        assert f"monitor: {len(fc16)} lines of {len(lines)} (filter: --fc 16)" in screen
        assert all(" 10 00 " in row for row in list_rows(screen))
        assert guard not in screen
        # w writes what the list holds: the filtered lines, as replay prints them
        shown = demo_log.parent / "fc16.txt"
        term.press("w")
        term.press(f"{shown}\r", 1.0)
        term.wait_for(lambda s: "wrote " in s)
        assert shown.read_text().splitlines() == fc16
        term.press("f")
        term.press("\x15\r", 1.0)  # ctrl+u, enter: no filter
        everything = demo_log.parent / "all.txt"
        term.press("w")
        term.press(f"{everything}\r", 1.0)
        term.wait_for(lambda s: f"wrote {len(lines)} lines" in s)
        assert everything.read_text().splitlines() == lines
        term.press("q")
        term.finish()
    finally:
        term.close()
    assert term.proc.returncode == 0


def test_replay_browse_needs_a_terminal(demo_log: Path) -> None:
    for extra in ([], ["--json"]):
        out = subprocess.run(
            [sys.executable, "-m", "mbmon", "replay", "--browse", str(demo_log), *extra],
            capture_output=True, text=True, timeout=60, cwd=REPO, stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )  # fmt: skip
        assert out.returncode == 2, out
        assert out.stdout == "" and "--browse" in out.stderr and "Traceback" not in out.stderr
