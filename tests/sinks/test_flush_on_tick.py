"""Every log reaches the disk within a second while the hub ticks (DESIGN rule 7).

Three levels: the sinks themselves (a hub that ticks after the last record
leaves no file empty); ``mbmon read -`` from a pipe that stalls (the hub ticks
while the pipe is silent) and ``mbmon sniff lo`` (needs root), both killed with
SIGKILL while records flow: every request older than one second is in every
file (.jsonl, .csv, .txt, .pcap, and .mcap, which flushes its chunks itself).
"""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from sink_records import REPO, session_items

from mbmon.format import View
from mbmon.hub import Hub
from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.pipeline import Pipeline
from mbmon.sinks.base import SinkContext, open_sink

FORMATS = (".jsonl", ".csv", ".txt", ".pcap", ".mcap")
ENV = {**os.environ, "PYTHONPATH": str(REPO), "TZ": "UTC"}
MBMON = [sys.executable, "-m", "mbmon"]


# --------------------------------------------------------------------------- sinks


@pytest.mark.parametrize("suffix", [".jsonl", ".csv", ".txt", ".pcap"])
def test_a_tick_puts_what_was_written_on_disk(tmp_path: Path, suffix: str) -> None:
    """Records written, then only ticks: the file holds them (a buffer of 256 KiB
    would otherwise keep them until it fills or the run ends)."""
    path = tmp_path / f"t{suffix}"
    sink = open_sink(path, SinkContext(view=View(), source="t"))
    hub = Hub(Pipeline(), [sink])
    try:
        for item in session_items():
            hub.feed(item)
        before = path.stat().st_size
        hub.tick(hub.now + 0.25)
        after = path.stat().st_size
    finally:
        hub.close()
    assert after == path.stat().st_size  # everything, not a part, reached the disk
    assert before < after, f"{suffix}: a tick left {before} bytes on disk"


# --------------------------------------------------------------------------- helpers


def _request_pdu(address: int) -> bytes:
    """Read Holding Registers, one register at ``address``: each request is unique."""
    return bytes([0x03, address >> 8, address & 0xFF, 0x00, 0x01])


def _logged_addresses(base: Path, extra: list[str]) -> dict[str, set[int]]:
    """Per format, the addresses of the requests the (killed) files ``base.*`` hold."""
    found: dict[str, set[int]] = {}
    lines = (base.with_suffix(".jsonl")).read_bytes().split(b"\n")[:-1]  # a cut last line
    found[".jsonl"] = {o["address"] for o in map(json.loads, lines) if o["kind"] == "request"}
    with open(base.with_suffix(".csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    found[".csv"] = {int(r["address"]) for r in rows if r["kind"] == "request" and r["line"]}
    text = base.with_suffix(".txt").read_text()
    found[".txt"] = {
        int(m.group(1).replace(" ", ""), 16)
        for m in re.finditer(r"  03 ([0-9A-F]{2} [0-9A-F]{2}) 00 01  \|", text)
    }
    for suffix, cmd in ((".pcap", ["read", *extra]), (".mcap", ["replay"])):
        out = subprocess.run(
            [*MBMON, cmd[0], str(base.with_suffix(suffix)), "--json", *cmd[1:]],
            capture_output=True,
            text=True,
            env=ENV,
            timeout=120,
        ).stdout
        found[suffix] = {
            o["address"] for o in map(json.loads, out.splitlines()) if o["kind"] == "request"
        }
    return found


def _write_args(base: Path) -> list[str]:
    return [arg for suffix in FORMATS for arg in ("-w", str(base.with_suffix(suffix)))]


def _check(base: Path, sent: list[tuple[float, int]], killed_at: float, extra: list[str]) -> None:
    old = {address for when, address in sent if when < killed_at - 1.0}
    assert len(old) >= 10, "the test sent too little to judge"
    for suffix, got in _logged_addresses(base, extra).items():
        lost = sorted(old - got)
        assert not lost, f"{suffix}: {len(lost)} requests older than 1 s missing: {lost[:10]}"


# --------------------------------------------------------------------------- read -


def test_piped_read_killed_has_every_record_older_than_a_second(tmp_path: Path) -> None:
    """``tcpdump -w - | mbmon read - -w ...``: packets at 20 per second for 2 s, then
    the pipe stalls (tcpdump waiting for traffic) for 1.5 s, then SIGKILL."""
    base = tmp_path / "cell"
    proc = subprocess.Popen(
        [*MBMON, "read", "-", "-q", *_write_args(base)],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=ENV,
    )
    assert proc.stdin is not None
    sent: list[tuple[float, int]] = []
    try:
        conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:502")
        pcap = PcapWriter(proc.stdin)
        ts = time.time()
        for frame in conv.open():
            pcap.write(ts, frame)
        pcap.flush()
        end = time.monotonic() + 60  # mbmon opens its logs once the first packet came
        while not all(base.with_suffix(s).exists() for s in FORMATS):
            assert proc.poll() is None and time.monotonic() < end, "mbmon read did not start"
            time.sleep(0.05)
        for tid in range(1, 41):
            pdu = _request_pdu(tid)
            mbap = tid.to_bytes(2, "big") + b"\0\0" + (len(pdu) + 1).to_bytes(2, "big") + b"\1"
            answer = bytes([0x03, 0x02, 0x00, tid & 0xFF])
            head = tid.to_bytes(2, "big") + b"\0\0" + (len(answer) + 1).to_bytes(2, "big") + b"\1"
            pcap.write(time.time(), conv.send(True, mbap + pdu))
            pcap.write(time.time(), conv.send(False, head + answer))
            pcap.flush()
            sent.append((time.monotonic(), tid))
            time.sleep(0.05)
        time.sleep(1.5)  # the pipe stalls: nothing more comes
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        killed_at = time.monotonic()
        proc.kill()
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdin.close()
        if proc.stderr is not None:
            proc.stderr.close()
    _check(base, sent, killed_at, [])


def test_piped_read_equals_reading_the_file(tmp_path: Path) -> None:
    """Through a pipe that stalls twice, ``read -`` prints what reading the file prints."""
    capture = REPO / "captures" / "hrss_ptp.pcap"
    if not capture.exists():
        pytest.skip("captures/hrss_ptp.pcap absent")
    expected = subprocess.run(
        [*MBMON, "read", str(capture), "--json", "--profile", "hrss"],
        capture_output=True,
        env=ENV,
        timeout=120,
        check=True,
    ).stdout
    data = capture.read_bytes()
    proc = subprocess.Popen(
        [*MBMON, "read", "-", "--json", "--profile", "hrss"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        env=ENV,
    )
    assert proc.stdin is not None
    for part in (data[: len(data) // 3], data[len(data) // 3 : 2 * len(data) // 3]):
        proc.stdin.write(part)
        proc.stdin.flush()
        time.sleep(0.8)
    out, _ = proc.communicate(data[2 * len(data) // 3 :], timeout=120)
    assert out == expected


# --------------------------------------------------------------------------- sniff


_SERVER = """
import logging, sys
logging.disable(logging.CRITICAL)
import warnings; warnings.simplefilter("ignore")
from pymodbus.server import StartTcpServer
from pymodbus.datastore import (ModbusServerContext, ModbusDeviceContext,
    ModbusSequentialDataBlock)
ctx = ModbusServerContext(devices=ModbusDeviceContext(
    hr=ModbusSequentialDataBlock(1, list(range(1000)))), single=True)
StartTcpServer(ctx, address=("127.0.0.1", int(sys.argv[1])))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _connect(port: int, timeout: float = 15.0) -> socket.socket:
    end = time.monotonic() + timeout
    while True:
        try:
            return socket.create_connection(("127.0.0.1", port), timeout=2)
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.05)


@pytest.fixture
def started() -> Iterator[Callable[..., subprocess.Popen[bytes]]]:
    procs: list[subprocess.Popen[bytes]] = []

    def start(*args: str, **kw: object) -> subprocess.Popen[bytes]:
        proc = subprocess.Popen(list(args), env=ENV, cwd=REPO, **kw)  # type: ignore[call-overload]
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        if proc.poll() is None:
            proc.kill()
        proc.wait()


@pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() != 0,
    reason="live capture needs root (an AF_PACKET socket); CI runs as root",
)
def test_sniff_killed_has_every_record_older_than_a_second(
    tmp_path: Path, started: Callable[..., subprocess.Popen[bytes]]
) -> None:
    pytest.importorskip("pymodbus")
    pytest.importorskip("scapy")
    port = _free_port()
    started(sys.executable, "-c", _SERVER, str(port), stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL)  # fmt: skip
    _connect(port).close()
    base = tmp_path / "live"
    sniffer = started(*MBMON, "sniff", "lo", "--port", str(port), "-q", *_write_args(base),
                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)  # fmt: skip
    end = time.monotonic() + 20
    while not all(base.with_suffix(s).exists() for s in FORMATS):  # the socket is open by then
        assert sniffer.poll() is None and time.monotonic() < end, "the sniffer did not start"
        time.sleep(0.05)
    time.sleep(0.5)
    sent: list[tuple[float, int]] = []
    with _connect(port) as sock:  # a client polling 5 times a second, then quiet
        for tid in range(1, 13):
            pdu = _request_pdu(tid)
            sock.sendall(
                tid.to_bytes(2, "big") + b"\0\0" + (len(pdu) + 1).to_bytes(2, "big") + b"\1" + pdu
            )
            answer = sock.recv(256)
            assert answer[:2] == tid.to_bytes(2, "big")
            sent.append((time.monotonic(), tid))
            time.sleep(0.2)
        time.sleep(1.5)  # the line is quiet; the connection stays open
        assert sniffer.poll() is None
        killed_at = time.monotonic()
        sniffer.send_signal(signal.SIGKILL)
        sniffer.wait(timeout=30)
    _check(base, sent, killed_at, ["--port", str(port)])
