"""`mbmon sniff lo`: a real capture of a pymodbus client and server on 127.0.0.1.

Runs the CLI as a subprocess (``python -m mbmon sniff lo --port N``) while a
pymodbus server (another subprocess) answers a pymodbus client, and checks the
exact frames, ``-c``, SIGINT/SIGTERM finishing the MCAP log (read back with the
``mcap`` library), and a timeout reported while the line is silent. Needs root
(an AF_PACKET socket); CI runs as root.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() != 0,
    reason="live capture needs root (an AF_PACKET socket); CI runs as root",
)

_SERVER = """
import logging, sys
logging.disable(logging.CRITICAL)
import warnings; warnings.simplefilter("ignore")
from pymodbus.server import StartTcpServer
from pymodbus.datastore import (ModbusServerContext, ModbusDeviceContext,
    ModbusSequentialDataBlock)
ctx = ModbusServerContext(devices=ModbusDeviceContext(
    hr=ModbusSequentialDataBlock(1, list(range(100))),
    co=ModbusSequentialDataBlock(1, [1, 0, 1, 1] * 25)), single=True)
StartTcpServer(ctx, address=("127.0.0.1", int(sys.argv[1])))
"""


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_port(port: int, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise AssertionError(f"nothing listens on 127.0.0.1:{port}")


@pytest.fixture
def modbus_server() -> Iterator[int]:
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-c", _SERVER, str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        _wait_port(port)
        time.sleep(0.2)  # the probe connection above is over before the sniffer starts
        yield port
    finally:
        proc.kill()
        proc.wait()


_STARTED: list[subprocess.Popen[bytes]] = []


@pytest.fixture(autouse=True)
def _no_leftover_sniffers() -> Iterator[None]:
    """A test that fails between starting a sniffer and stopping it leaves none running."""
    yield
    while _STARTED:
        proc = _STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


class Sniffer:
    """``python -m mbmon sniff ...`` as a subprocess, started and ready to capture."""

    def __init__(self, *args: str, ready: Path | None = None) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "sniff", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=_env(),
            cwd=REPO,
        )
        _STARTED.append(self.proc)
        self.err = b""
        self.out = b""
        self._wait_ready(ready)

    def _wait_ready(self, ready_file: Path | None) -> None:
        """Until the "sniffing" line (or, with -q, the log file: the socket is open by then)."""
        assert self.proc.stderr is not None
        end = time.monotonic() + 15
        while b"sniffing" not in self.err:
            if ready_file is not None and ready_file.exists():
                return
            if self.proc.poll() is not None or time.monotonic() > end:
                rest = self.proc.stderr.read() if self.proc.poll() is not None else b""
                raise AssertionError(f"sniffer did not start: {(self.err + rest).decode()}")
            ready, _, _ = select.select([self.proc.stderr], [], [], 0.1)
            if ready:
                self.err += os.read(self.proc.stderr.fileno(), 4096)

    def read_until(self, needle: bytes, timeout: float) -> float:
        """Read stdout until ``needle`` appears; return when (monotonic) it did."""
        assert self.proc.stdout is not None
        end = time.monotonic() + timeout
        while needle not in self.out:
            left = end - time.monotonic()
            if left <= 0:
                raise AssertionError(f"{needle!r} not seen; stdout: {self.out.decode()}")
            ready, _, _ = select.select([self.proc.stdout], [], [], left)
            if ready:
                data = os.read(self.proc.stdout.fileno(), 65536)
                if not data:
                    raise AssertionError(f"sniffer ended; stdout: {self.out.decode()}")
                self.out += data
        return time.monotonic()

    def finish(self, sig: int | None = signal.SIGINT, timeout: float = 10.0) -> tuple[str, str]:
        if sig is not None:
            self.proc.send_signal(sig)
        out, err = self.proc.communicate(timeout=timeout)
        return (self.out + out).decode(), (self.err + err).decode()


def _client_session(port: int, transactions: int | None = None) -> None:
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient("127.0.0.1", port=port)
    assert client.connect()
    try:
        steps = [
            lambda: client.read_holding_registers(0, count=3),
            lambda: client.write_register(5, 1234),
            lambda: client.read_coils(0, count=4),
            lambda: client.write_registers(10, [7, 8]),
            lambda: client.read_holding_registers(200, count=2),  # exception 02
        ]
        for step in steps[:transactions]:
            step()
    finally:
        client.close()


_EXPECTED = [
    ("request", "03 00 00 00 03"),
    ("response", "03 06 00 00 00 01 00 02"),
    ("request", "06 00 05 04 D2"),
    ("response", "06 00 05 04 D2"),
    ("request", "01 00 00 00 04"),
    ("response", "01 01 0D"),
    ("request", "10 00 0A 00 02 04 00 07 00 08"),
    ("response", "10 00 0A 00 02"),
    ("request", "03 00 C8 00 02"),
    ("exception", "83 02"),
]


def _frames(stdout: str) -> list[tuple[str, str]]:
    objs = [json.loads(line) for line in stdout.splitlines() if line.strip()]
    return [
        (o["kind"], o["pdu"]) for o in objs if o["kind"] in ("request", "response", "exception")
    ]


def _read_mcap(path: Path) -> dict[str, int]:
    from mcap.reader import make_reader

    counts: dict[str, int] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None, "the MCAP log has no summary: it was not finished"
        for _schema, channel, _message in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def test_sniff_loopback_exact_frames_sigint_finishes_log(modbus_server: int, tmp_path: Path):
    log = tmp_path / "live.mcap"
    sniffer = Sniffer("lo", "--port", str(modbus_server), "--json", "-w", str(log))
    _client_session(modbus_server)
    sniffer.read_until(b'"83 02"', timeout=5)
    out, err = sniffer.finish(signal.SIGINT)
    assert sniffer.proc.returncode == 0, err
    assert _frames(out) == _EXPECTED
    objs = [json.loads(line) for line in out.splitlines()]
    assert objs[0]["kind"] == "event" and "Connect 127.0.0.1:" in objs[0]["line"]
    port = modbus_server  # the default kernel filter: port 502 and the extra port
    assert f"(filter: tcp port 502 or udp port 502 or tcp port {port} or udp port {port})" in err
    assert "0 dropped" in err
    assert "10 frames (5 requests, 5 answered, 1 exceptions, 0 unanswered" in err  # as read
    counts = _read_mcap(log)
    assert counts["/modbus/frames"] == 10
    assert counts["/modbus/monitor"] >= 10
    # the log says by itself whether the capture was complete: the kernel's counters
    from mcap.reader import make_reader

    with open(log, "rb") as f:
        events = [
            json.loads(message.data)
            for _schema, channel, message in make_reader(f).iter_messages()
            if channel.topic == "/mbmon/events"
        ]
    kernel = [e["info"] for e in events if "kernel_drops" in e.get("info", {})]
    assert kernel and kernel[-1]["interface"] == "lo" and kernel[-1]["kernel_drops"] == 0
    assert kernel[-1]["complete"] is True and kernel[-1]["packets"] >= 10


def test_sniff_count_stops(modbus_server: int, tmp_path: Path):
    log = tmp_path / "four.mcap"
    args = ("-i", "lo", "--port", str(modbus_server), "--json", "-c", "4", "-w", str(log))
    sniffer = Sniffer(*args)
    _client_session(modbus_server)
    out, err = sniffer.finish(sig=None, timeout=10)
    assert sniffer.proc.returncode == 0, err
    assert _frames(out) == _EXPECTED[:4]
    assert _read_mcap(log)["/modbus/frames"] == 4  # the log stops at the same frame


def test_sniff_filters_choose_what_is_shown_and_what_count_counts(
    modbus_server: int, tmp_path: Path
):
    """``read``'s filters on a live capture: ``--fc 6,16 -c 2`` shows the two frames of
    the Write Single Register exchange only and stops there; the log keeps every
    record up to that point (the reads before it too), the summary counts them."""
    log = tmp_path / "writes.mcap"
    args = ("lo", "--port", str(modbus_server), "--json", "--fc", "6,16", "-c", "2")
    sniffer = Sniffer(*args, "-w", str(log))
    _client_session(modbus_server)
    out, err = sniffer.finish(sig=None, timeout=10)
    assert sniffer.proc.returncode == 0, err
    objs = [json.loads(line) for line in out.splitlines()]
    assert [(o["kind"], o["pdu"]) for o in objs] == _EXPECTED[2:4]  # no connect line either
    assert _read_mcap(log)["/modbus/frames"] == 4
    assert "4 frames (2 requests, 2 answered" in err


def test_sniff_sigterm_finishes_log(modbus_server: int, tmp_path: Path):
    log = tmp_path / "term.mcap"
    sniffer = Sniffer("lo", "--port", str(modbus_server), "-q", "-w", str(log), ready=log)
    _client_session(modbus_server, transactions=2)
    time.sleep(0.5)
    out, err = sniffer.finish(signal.SIGTERM)
    assert sniffer.proc.returncode == 0, err
    assert out == "" and "sniffed" not in err  # -q: nothing on stdout, no summary
    counts = _read_mcap(log)
    assert counts["/modbus/frames"] == 4
    from mbmon.io.mcap.reader import McapLog
    from mbmon.io.replay import raw_items
    from mbmon.model import Chunk

    with McapLog(log) as mlog:  # format 4: a one-ADU chunk's message is left out, rebuilt
        assert sum(isinstance(c, Chunk) for c in raw_items(mlog)) >= 4


def test_unanswered_request_reported_at_timeout_on_a_silent_line():
    port = _free_port()
    silent = socket.socket()
    silent.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    silent.bind(("127.0.0.1", port))
    silent.listen()
    sniffer = Sniffer("lo", "--port", str(port), "--plain", "--timeout", "0.5")
    try:
        client = socket.create_connection(("127.0.0.1", port))
        conn, _ = silent.accept()
        client.sendall(bytes.fromhex("0001 0000 0006 01 03 0000 0002"))
        sent = time.monotonic()
        seen = sniffer.read_until(b"No response to Read Holding Registers", timeout=5)
        assert seen - sent <= 0.5 + 1.0, f"reported after {seen - sent:.2f} s"
        assert b"03 00 00 00 02" in sniffer.out
    finally:
        _out, err = sniffer.finish(signal.SIGINT)
        silent.close()
    conn.close()  # held open until now: no FIN, no other traffic before the timeout
    client.close()
    assert "1 frames (1 requests, 0 answered, 0 exceptions, 1 unanswered" in err


def test_sniff_unknown_interface_names_the_available_ones():
    proc = subprocess.run(
        [sys.executable, "-m", "mbmon", "sniff", "no-such-if0"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=30,
    )
    assert proc.returncode == 1
    assert "no interface 'no-such-if0'; available:" in proc.stderr and "lo" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_sniff_list_shows_loopback():
    proc = subprocess.run(
        [sys.executable, "-m", "mbmon", "sniff", "--list"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=30,
    )
    assert proc.returncode == 0
    assert any(line.split()[0] == "lo" for line in proc.stdout.splitlines())


@pytest.mark.skipif(shutil.which("setpriv") is None, reason="setpriv (util-linux) is missing")
def test_sniff_without_capture_rights_says_what_is_needed():
    drop = "-net_raw,-net_admin"
    setpriv = ["setpriv", f"--bounding-set={drop}", f"--inh-caps={drop}"]
    proc = subprocess.run(
        [*setpriv, sys.executable, "-m", "mbmon", "sniff", "lo"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=30,
    )
    assert proc.returncode == 1, proc.stderr
    assert "needs root, or the capabilities CAP_NET_RAW and CAP_NET_ADMIN" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_sniff_bad_filter_is_a_clear_error():
    proc = subprocess.run(
        [sys.executable, "-m", "mbmon", "sniff", "lo", "-f", "tcp port"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=30,
    )
    assert proc.returncode == 1
    assert "bad capture filter 'tcp port'" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_drops_while_the_socket_is_set_up_are_not_the_captures():
    """scapy opens its socket with a receive buffer of 0 while it compiles and attaches
    the filter, so busy loopback traffic in those milliseconds is counted as kernel
    drops before the capture has begun. Those are not packets the capture lost: the
    summary's "dropped" (and "capture INCOMPLETE") start when the capture does."""
    import threading

    from mbmon.sources.sniff import PacketCapture

    stop = threading.Event()

    def flood() -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            target = ("127.0.0.1", _free_port())
            while not stop.is_set():
                for _ in range(100):
                    s.sendto(b"x" * 200, target)

    flooder = threading.Thread(target=flood, daemon=True)
    flooder.start()
    capture = PacketCapture("lo", f"udp port {_free_port()}", lambda batch: None)
    try:
        capture.open()
    finally:
        stop.set()
        flooder.join()
    try:
        stats = capture.kernel_stats()
    finally:
        capture.stop()
    assert stats.drops == 0, stats


def test_a_terminal_gets_the_live_screen_with_kernel_drops_and_the_robot_panel():
    """``sniff lo --profile hrss`` on a real pseudo-terminal (read back through pyte, a
    VT100 emulator) while the sim robot runs the manual's program on 127.0.0.1: the
    monitor's header has the kernel drop count and the open connections (one opened
    before the capture began counts too), the robot panel the axes, the last command
    and the written command registers (R200..R251) by their HRSS names."""
    import fcntl
    import pty
    import re
    import struct
    import termios

    import pyte

    from mbmon.sim import SimServer, run_program

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 60, 220, 0, 0))
    screen = pyte.Screen(220, 60)
    stream = pyte.ByteStream(screen)
    shown = b""
    with SimServer() as sim, socket.create_connection((sim.host, sim.port)) as early:
        time.sleep(0.2)  # its handshake is over before the capture starts
        proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "sniff", "lo", "--port", str(sim.port),
             "--profile", "hrss"],
            stdin=slave, stdout=slave, stderr=subprocess.PIPE, cwd=REPO,
            env={**_env(), "COLUMNS": "220", "LINES": "60", "TERM": "xterm"},
        )  # fmt: skip
        _STARTED.append(proc)
        os.close(slave)

        def drain(seconds: float) -> bytes:
            """What the screen draws in the next ``seconds`` (it redraws every 0.25 s)."""
            got = b""
            end = time.monotonic() + seconds
            while (left := end - time.monotonic()) > 0:
                if select.select([master], [], [], left)[0]:
                    try:
                        part = os.read(master, 65536)
                    except OSError:
                        break
                    if not part:
                        break
                    got += part
                    stream.feed(part)
            return got

        assert proc.stderr is not None
        assert b"sniffing" in proc.stderr.readline()
        early.sendall(bytes.fromhex("0001 0000 0006 01 04 020C 0001"))  # IR524, mid-stream
        assert early.recv(64)[7:9] == b"\x04\x02"
        done = threading.Event()
        runner = threading.Thread(
            target=lambda: (run_program(sim.host, sim.port, extras=False), done.set()),
            daemon=True,
        )
        runner.start()
        while not done.is_set():
            shown += drain(0.1)
        runner.join()
        shown += drain(1.0)  # a few ticks: the screen shows the end of the program
        last = "\n".join(screen.display)  # the screen as the terminal shows it
        proc.send_signal(signal.SIGINT)
        end = time.monotonic() + 20
        while proc.poll() is None and time.monotonic() < end:
            shown += drain(0.1)
        shown += drain(0.2)
        proc.wait(5)
        os.close(master)
    assert proc.returncode == 0
    assert "mbmon sniff lo " in last
    # the robot panel (the right-hand column) as one text, its lines joined
    rows = last.splitlines()
    top = next(i for i, r in enumerate(rows) if "╭─ robot" in r)
    left = rows[top].index("╭─ robot")
    panel = []
    for row in rows[top + 1 :]:
        cell = row[left + 1 : left + 45]
        if cell.startswith("─"):
            break
        panel.append(cell.strip())
    robot = " ".join(panel)
    assert "kernel drops 0" in last
    assert "open connections 1 " in last  # the early one; the program's has closed
    assert re.search(r"A1 +90\.000", last)  # the program's PTP {A1 90}, read back from IR300
    assert "speed " in last and "motion state " in last
    assert re.search(r"last command \(.+\): PTP \{A1 90, .*\[(executing|success)", robot)
    assert re.search(r"command registers R200\.\.R251 as\s+written", robot), robot
    assert "R200 execute Execute (1)" in robot and "R201 command PTP (0)" in robot
    assert "R203..R204 A1 90 deg" in robot and "R215 speed 50%" in robot
