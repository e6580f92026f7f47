"""Every source of the contract (mbmon.sources.base) over real inputs: the project's
captures and raw RTU dumps, an MCAP log written by ``mbmon read -w``, a FIFO, bytes
typed by hand, a socat pty pair (serial) and the proxy in front of ``mbmon sim``
(thread and child process). Each runs through ``run_sources`` into ``read``'s console;
open failures are one line (SourceError) before any output exists."""

from __future__ import annotations

import io
import os
import shutil
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from mbmon_cli import mbmon

from mbmon.format import View
from mbmon.hub import Hub
from mbmon.model import EventKind, Transport
from mbmon.pipeline import Pipeline
from mbmon.protocol.crc import crc_bytes
from mbmon.sinks.console import ConsoleListener
from mbmon.sources.base import Source, SourceError, run_sources
from mbmon.sources.files import CaptureFileSource, McapLogSource, RawRtuSource
from mbmon.sources.pcapfile import read_capture
from mbmon.sources.serial import SerialSettings
from mbmon.sources.serialbus import SerialBusSource, SerialOpenError
from mbmon.sources.typed import TypedFrameSource

REPO = Path(__file__).resolve().parents[2]
CAPTURES = REPO / "captures"


class Events:
    """Keeps the source events a run was given (STATS, NOTICE)."""

    def __init__(self) -> None:
        self.events: list = []

    def on_event(self, event) -> None:
        self.events.append(event)


def run(*sources: Source, live_stop: float | None = None) -> tuple[str, Hub, Events]:
    """``sources`` through one hub into ``read``'s console; the text and the hub."""
    out = io.StringIO()
    events = Events()
    hub = Hub(Pipeline(), [ConsoleListener(out, View()), events])
    for source in sources:
        source.open(hub)
    run_sources(hub, list(sources))
    hub.close()
    return out.getvalue(), hub, events


def lines_of_reference(path: Path) -> str:
    """What the reference path gives for a capture: read_capture through a hub."""
    out = io.StringIO()
    hub = Hub(Pipeline(), [ConsoleListener(out, View())])
    hub.run_items(read_capture(path))
    hub.close()
    return out.getvalue()


# --------------------------------------------------------------------------- files


def test_capture_file_source_gives_the_readers_records() -> None:
    path = CAPTURES / "sim_functions.pcap"
    source = CaptureFileSource(path)
    assert source.mode == "file"
    text, hub, _ = run(source)
    assert text and text == lines_of_reference(path)
    assert source.stats()["packets"] > 0
    assert source.summary()[0].endswith("streams")
    assert not hub.errors


def test_capture_file_source_open_errors_are_one_line(tmp_path: Path) -> None:
    missing = CaptureFileSource(tmp_path / "nope.pcap")
    with pytest.raises(SourceError, match=r"nope.pcap: cannot open \(No such file"):
        missing.open(Hub())
    text = tmp_path / "notes.txt"
    text.write_text("not a capture\n")
    with pytest.raises(SourceError) as info:
        CaptureFileSource(text).open(Hub())
    assert "\n" not in str(info.value) and "notes.txt" in str(info.value)


def test_capture_file_source_stop_closes_the_capture() -> None:
    """A run that ends early (``-c``, a closed stdout) or a source given up before its
    run leaves no capture open: ``stop`` closes it, and stopping again does nothing."""

    def fds() -> int:
        return len(os.listdir("/proc/self/fd"))

    before = fds()
    source = CaptureFileSource(CAPTURES / "sim_functions.pcap")
    source.open(Hub())
    assert fds() == before + 1
    source.stop()
    assert fds() == before
    source.stop()
    assert fds() == before


def test_a_fifo_is_a_stream_source(tmp_path: Path) -> None:
    path = CAPTURES / "sim_functions.pcap"
    fifo = tmp_path / "cap.fifo"
    os.mkfifo(fifo)

    def feed() -> None:
        with open(fifo, "wb") as f:
            f.write(path.read_bytes())

    writer = threading.Thread(target=feed, daemon=True)
    writer.start()
    source = CaptureFileSource(fifo)
    assert source.mode == "stream"
    text, _, _ = run(source)
    writer.join(10)
    assert text == lines_of_reference(path)


def test_raw_rtu_source_takes_its_stream_id_from_the_hub(tmp_path: Path) -> None:
    req = b"\x01\x03\x00\x00\x00\x01"
    resp = b"\x01\x03\x02\x00\x2a"
    dump = tmp_path / "bus.bin"
    dump.write_bytes(req + crc_bytes(req) + resp + crc_bytes(resp))
    first, second = RawRtuSource(dump), RawRtuSource(dump)
    text, _, _ = run(first, second)
    lines = text.splitlines()
    assert len(lines) == 4
    assert lines[0].endswith("03 00 00 00 01  | Read Holding Registers 0")
    assert lines[1].endswith("03 02 00 2A  | Read Holding Registers 0 = 42")
    assert first.summary() == [f"15 bytes read from {dump}"]
    with pytest.raises(SourceError, match="cannot open"):
        RawRtuSource(tmp_path / "missing.bin").open(Hub())


def test_mcap_log_source_decodes_what_was_recorded(tmp_path: Path) -> None:
    path = CAPTURES / "sim_functions.pcap"
    log = tmp_path / "run.mcap"
    done = mbmon("read", path, "-q", "-w", log)
    assert done.returncode == 0, done.stderr
    source = McapLogSource(log)
    text, _, _ = run(source)
    assert text == lines_of_reference(path)
    assert source.summary()[0].startswith("finished log")
    with pytest.raises(SourceError, match="not an MCAP"):
        McapLogSource(path).open(Hub())


# --------------------------------------------------------------------------- typed bytes


def rtu(hextext: str) -> bytes:
    body = bytes.fromhex(hextext)
    return body + crc_bytes(body)


@pytest.mark.parametrize(
    ("data", "framing", "response", "line"),
    [
        (rtu("01 03 00 00 00 0A"), "rtu", False, "03 00 00 00 0A  | Read Holding Registers 0..9"),
        (rtu("01 03 02 00 2A"), "rtu", True, "03 02 00 2A  | Read Holding Registers = 42"),
        (
            bytes.fromhex("02 01 2C 00 05"),
            "pdu",
            False,
            "02 01 2C 00 05  | Read Discrete Inputs 300..304",
        ),
        (
            bytes.fromhex("00 01 00 00 00 06 01 03 00 00 00 01"),
            "tcp",
            False,
            "03 00 00 00 01  | Read Holding Registers 0",
        ),
        (bytes.fromhex("83 02"), "pdu", True, "83 02"),
    ],
)
def test_typed_bytes_are_decoded_by_the_one_flow(
    data: bytes, framing: str, response: bool, line: str
) -> None:
    source = TypedFrameSource(data, framing, response=response)  # type: ignore[arg-type]
    text, _, _ = run(source)
    first = text.splitlines()[0]
    assert line in first, first
    assert first.startswith("#0 ")  # untimed: record numbers, no clock


def test_typed_rtu_bytes_with_a_bad_crc_are_that_frame() -> None:
    """The bytes typed are one ADU: a bad CRC is that frame's verdict, not bus noise,
    and a request typed alone is never reported unanswered."""
    data = bytes.fromhex("01 03 00 00 00 0A C5 CE")
    text, hub, _ = run(TypedFrameSource(data, "rtu"))
    assert "noise" not in text and "No response" not in text
    assert text.splitlines()[0].startswith("#0 ")
    assert "03 00 00 00 0A" in text and hub.records == 1


# --------------------------------------------------------------------------- serial


needs_socat = pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")


@needs_socat
def test_serial_bus_source_over_a_pty_pair() -> None:
    from socat_ptys import pty_pair

    with pty_pair() as (a, b):
        out = io.StringIO()
        events = Events()
        hub = Hub(Pipeline(), [ConsoleListener(out, View()), events])
        source = SerialBusSource([b], SerialSettings(115200))
        source.open(hub)
        assert source.stream is not None and source.stream.transport is Transport.RTU
        runner = threading.Thread(target=run_sources, args=(hub, [source]), daemon=True)
        runner.start()
        fd = os.open(a, os.O_WRONLY | os.O_NOCTTY)
        try:
            os.write(fd, rtu("01 03 00 00 00 01"))
            time.sleep(0.05)
            os.write(fd, rtu("01 03 02 00 2A"))
        finally:
            os.close(fd)
        deadline = time.monotonic() + 20
        while "= 42" not in out.getvalue() and time.monotonic() < deadline:
            time.sleep(0.05)
        hub.stop()
        runner.join(20)
        assert not runner.is_alive()
        hub.close()
    assert "03 02 00 2A  | Read Holding Registers 0 = 42" in out.getvalue()
    assert source.stats()["CRC failures"] == 0
    stats = [e for e in events.events if e.kind is EventKind.STATS]
    assert stats and stats[-1].info["frames"] == 2 and stats[-1].info["bus"] == b
    summary = source.summary()
    assert summary[0].startswith(f"{b}: ") and summary[0].endswith(" reads, 15 bytes")
    assert any(line.startswith(f"bus {b} (115200 8N1)") for line in summary)
    assert all(not tap._thread.is_alive() for tap in source.taps if tap._thread is not None)


def test_a_serial_port_that_cannot_open_is_one_line(tmp_path: Path) -> None:
    source = SerialBusSource([str(tmp_path / "ttyNONE")], SerialSettings())
    with pytest.raises(SerialOpenError) as info:
        source.open(Hub())
    assert info.value.port.endswith("ttyNONE")
    assert "No such file" in str(info.value) and "\n" not in str(info.value)


# --------------------------------------------------------------------------- proxy


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def sim_server() -> Iterator[int]:
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "sim", "--listen", f"127.0.0.1:{port}", "-q"],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.1)
        else:
            pytest.fail("mbmon sim did not listen")
        yield port
    finally:
        proc.kill()
        proc.wait()


def read_through(port: int, tid: int) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, 0, 2))
        head = b""
        while len(head) < 7:
            head += sock.recv(7 - len(head))
        rest = b""
        need = struct.unpack(">H", head[4:6])[0] - 1
        while len(rest) < need:
            rest += sock.recv(need - len(rest))
        return head + rest


@pytest.mark.parametrize("process", [False, True], ids=["thread", "process"])
def test_proxy_source_observes_what_it_forwards(process: bool) -> None:
    from mbmon.proxy.config import ProxyConfig
    from mbmon.sources.proxy import ProxySource

    with sim_server() as up:
        out = io.StringIO()
        hub = Hub(Pipeline(), [ConsoleListener(out, View())])
        config = ProxyConfig(upstream_host="127.0.0.1", upstream_port=up, listen_port=0)
        source = ProxySource(config, process=process)
        source.open(hub)
        assert source.address is not None
        runner = threading.Thread(target=run_sources, args=(hub, [source]), daemon=True)
        runner.start()
        answer = read_through(source.address[1], 7)
        assert answer[:2] == b"\x00\x07" and answer[7] == 3
        deadline = time.monotonic() + 20
        while "[u1 t7]  03 04" not in out.getvalue() and time.monotonic() < deadline:
            time.sleep(0.05)
        hub.stop()
        runner.join(30)
        assert not runner.is_alive()
        hub.close()
    text = out.getvalue()
    assert "[u1 t7]  03 00 00 00 02  | Read Holding Registers 0..1" in text
    assert "[u1 t7]  03 04" in text
    assert source.stats()["upstream"] == "up"  # the engine's figures
    summary = source.summary()
    assert "requests 1, responses 1" in summary and "clients 1 (refused 0, dropped 0)" in summary
    assert not source.ended_unexpectedly


def test_a_proxy_that_cannot_listen_is_one_line() -> None:
    from mbmon.proxy.config import ProxyConfig
    from mbmon.sources.proxy import ProxySource, ProxyStartError

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        config = ProxyConfig(upstream_host="127.0.0.1", upstream_port=1, listen_port=port)
        source = ProxySource(config)
        with pytest.raises(ProxyStartError) as info:
            source.open(Hub())
    assert isinstance(info.value.error, OSError)
    assert "in use" in str(info.value).lower()
