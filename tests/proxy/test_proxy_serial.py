"""The proxy's serial variants on real pty pairs (socat) with pymodbus peers.

TCP -> RTU (Modbus/TCP clients reaching an RTU slave), RTU <-> RTU (between an
RTU master and an RTU slave on two "adapters") and RTU -> TCP (an RTU master
reaching a Modbus/TCP server): the answers are the ones the server gives
directly, byte for byte; the gateway rules (0x0B on timeout and 0x0A when the
bus is gone for TCP clients, silence for RTU masters); the write guard with an
RTU exception frame; both sides reach the hub (the RTU bus as an RTU stream).
"""

from __future__ import annotations

import os
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from socat_ptys import pty_pair

from mbmon.protocol.rtu import encode_rtu

pytestmark = pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
BAUD = 115200

#: A pymodbus server with plain blocks (value = address) on TCP or RTU:
#: ``python -c SERVER tcp PORT`` or ``python -c SERVER rtu DEVICE``; prints "ready".
SERVER = r"""
import asyncio, sys, logging
logging.disable(logging.CRITICAL)
import warnings; warnings.simplefilter("ignore")
from pymodbus import FramerType
from pymodbus.datastore import (ModbusDeviceContext, ModbusSequentialDataBlock,
                                ModbusServerContext)
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
def block(): return ModbusSequentialDataBlock(1, list(range(1000)))
dev = ModbusDeviceContext(di=block(), co=block(), hr=block(), ir=block())
ctx = ModbusServerContext(devices=dev, single=True)
async def main():
    if sys.argv[1] == "tcp":
        server = ModbusTcpServer(ctx, address=("127.0.0.1", int(sys.argv[2])))
    else:
        server = ModbusSerialServer(ctx, framer=FramerType.RTU, port=sys.argv[2],
                                    baudrate=115200)
    await server.serve_forever(background=True)
    print("ready", flush=True)
    await asyncio.Event().wait()
asyncio.run(main())
"""


@contextmanager
def server(kind: str, where: str) -> Iterator[None]:
    proc = subprocess.Popen(
        [sys.executable, "-c", SERVER, kind, where], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        yield
    finally:
        proc.kill()
        proc.wait()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Proxy:
    """``python -m mbmon proxy ARGS --plain`` in its own process; ``stop()`` = Ctrl-C."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "proxy", "--plain", "--baud", str(BAUD), *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        assert self.proc.stderr is not None
        line = self.proc.stderr.readline()
        assert "listening on" in line, line + self.proc.stderr.read()
        m = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
        self.port = int(m.group(1)) if m else 0

    def stop(self) -> tuple[str, str]:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        out, err = self.proc.communicate(timeout=20)
        assert self.proc.returncode == 0, err
        return out, err


@contextmanager
def proxy(*args: str) -> Iterator[Proxy]:
    p = Proxy(*args)
    try:
        yield p
    finally:
        if p.proc.poll() is None:
            p.proc.kill()
            p.proc.communicate()


# --------------------------------------------------------------------------- clients


def session(client: Any) -> None:
    """Several function codes; the writes write the same each time, so from the second
    session on every session gets the same answers."""
    client.read_coils(0, count=19)
    client.read_discrete_inputs(3, count=7)
    client.read_holding_registers(0, count=10)
    client.read_input_registers(5, count=3)
    client.write_coil(2, True)
    client.write_register(5, 1234)
    client.write_coils(10, [True, False, True])
    client.write_registers(20, [7, 8, 9])
    client.read_holding_registers(0, count=30)
    client.read_holding_registers(990, count=100)  # beyond the block: an exception answer


def tcp_session(port: int) -> list[bytes]:
    """The raw Modbus/TCP answers of :func:`session` through ``port``."""
    from pymodbus.client import ModbusTcpClient

    got: list[bytes] = []

    def trace(sending: bool, data: bytes) -> bytes:
        if not sending:
            got.append(bytes(data))
        return data

    client = ModbusTcpClient("127.0.0.1", port=port, trace_packet=trace, timeout=3, retries=0)
    assert client.connect()
    try:
        session(client)
    finally:
        client.close()
    return got


def rtu_session(device: str) -> list[bytes]:
    """The raw RTU answers (unit id + PDU + CRC) of :func:`session` on ``device``."""
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    got: list[bytes] = []

    def trace(sending: bool, data: bytes) -> bytes:
        if not sending:
            got.append(bytes(data))
        return data

    client = ModbusSerialClient(
        device, framer=FramerType.RTU, baudrate=BAUD, timeout=2, retries=0, trace_packet=trace
    )
    assert client.connect()
    try:
        session(client)
    finally:
        client.close()
    return got


def pdus_tcp(answers: list[bytes]) -> list[bytes]:
    return [a[7:] for a in answers]


def pdus_rtu(answers: list[bytes]) -> list[bytes]:
    return [a[1:-2] for a in answers]


class RawMaster:
    """An RTU master on a pty: writes a frame, collects what comes back for a while."""

    def __init__(self, device: str) -> None:
        from mbmon.sources.serial import SerialSettings, open_port

        self.port = open_port(device, SerialSettings(BAUD))
        self.fd = self.port.fileno()

    def ask(self, unit: int, pdu: bytes, wait: float = 1.0) -> bytes:
        os.write(self.fd, encode_rtu(unit, pdu))
        got = b""
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            if select.select([self.fd], [], [], 0.05)[0]:
                got += os.read(self.fd, 512)
        return got

    def close(self) -> None:
        self.port.close()


def mbap(tid: int, pdu: bytes, unit: int = 1) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def tcp_rpc(sock: socket.socket, tid: int, pdu: bytes) -> bytes:
    sock.sendall(mbap(tid, pdu))
    buf = b""
    while len(buf) < 7 or len(buf) < 6 + struct.unpack(">H", buf[4:6])[0]:
        part = sock.recv(300)
        assert part, "the proxy closed the connection"
        buf += part
    return buf


# --------------------------------------------------------------------------- TCP -> RTU


def test_tcp_to_rtu_answers_as_the_slave_does_and_both_sides_are_observed() -> None:
    with pty_pair() as (bus_proxy, bus_slave), server("rtu", bus_slave):
        rtu_session(bus_proxy)  # the writes done once
        direct = rtu_session(bus_proxy)
        with proxy("--upstream-serial", bus_proxy, "--listen", "127.0.0.1:0") as p:
            through = tcp_session(p.port)
            out, err = p.stop()
    assert len(direct) == 10 and len(through) == 10
    assert pdus_tcp(through) == pdus_rtu(direct)
    assert through[-1][7:9] == b"\x83\x02"  # the slave's own exception, passed on
    # the hub saw the TCP client's stream and the RTU bus (the robot: the bus's slave)
    assert re.search(r"Receive from client  \[u1 t\d+\]  03 00 00 00 0A", out), out
    bus_lines = [line for line in out.splitlines() if "[u1]" in line]
    assert sum("Receive from client" in line for line in bus_lines) == 10, out
    assert sum("Send to client" in line for line in bus_lines) == 10, out
    assert "requests 10, responses 10" in err


def test_tcp_to_rtu_clients_take_turns_on_the_bus() -> None:
    """Four TCP clients at once, each pipelining 30 requests: every answer is its
    own (transaction id and registers), and no client waits for another's 30."""
    with pty_pair() as (bus_proxy, bus_slave), server("rtu", bus_slave):
        with proxy("--upstream-serial", bus_proxy, "--listen", "127.0.0.1:0", "-q") as p:
            firsts: dict[int, float] = {}
            errors: list[str] = []
            t0 = time.monotonic()

            def client(n: int) -> None:
                with socket.create_connection(("127.0.0.1", p.port), timeout=10) as s:
                    s.sendall(b"".join(
                        mbap(1000 * n + i, struct.pack(">BHH", 3, 10 * n + i, 2))
                        for i in range(30)
                    ))  # fmt: skip
                    buf = b""
                    for i in range(30):
                        while len(buf) < 13:
                            buf += s.recv(4096)
                        if i == 0:
                            firsts[n] = time.monotonic() - t0
                        answer, buf = buf[:13], buf[13:]
                        a = 10 * n + i
                        if answer != mbap(1000 * n + i, b"\x03\x04" + struct.pack(">HH", a, a + 1)):
                            errors.append(f"client {n} request {i}: {answer.hex()}")

            threads = [threading.Thread(target=client, args=(n,)) for n in range(4)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(30)
            total = time.monotonic() - t0
            p.stop()
    assert errors == []
    assert len(firsts) == 4
    # round robin: every client's first answer comes long before the 120 are done
    assert max(firsts.values()) < total / 2, (firsts, total)


def test_tcp_to_rtu_silent_slave_0B_then_port_gone_0A() -> None:
    pair = pty_pair()
    bus_proxy, _nobody = pair.__enter__()
    try:
        with proxy("--upstream-serial", bus_proxy, "--listen", "127.0.0.1:0",
                   "--timeout", "0.4") as p:  # fmt: skip
            with socket.create_connection(("127.0.0.1", p.port), timeout=5) as s:
                t0 = time.monotonic()
                assert tcp_rpc(s, 5, bytes.fromhex("0300000002")) == mbap(5, b"\x83\x0b")
                assert 0.35 < time.monotonic() - t0 < 1.5
                # the client stays connected: the next request gets its own 0x0B
                assert tcp_rpc(s, 6, bytes.fromhex("0400000001")) == mbap(6, b"\x84\x0b")
                pair.__exit__(None, None, None)  # the adapter is unplugged
                pair = None
                time.sleep(0.3)
                t0 = time.monotonic()
                assert tcp_rpc(s, 7, bytes.fromhex("0300000002")) == mbap(7, b"\x83\x0a")
                assert time.monotonic() - t0 < 1.0  # 0x0A (not 0x0B): at once, not at the timeout
            out, err = p.stop()
    finally:
        if pair is not None:
            pair.__exit__(None, None, None)
    assert "0x0B 2" in err and "0x0A 1" in err, err
    assert "lost" in out and "answering 0x0A" in out


def test_tcp_to_rtu_read_only_refuses_writes_before_the_bus() -> None:
    with pty_pair() as (bus_proxy, bus_slave), server("rtu", bus_slave):
        with proxy("--upstream-serial", bus_proxy, "--listen", "127.0.0.1:0",
                   "--read-only") as p:  # fmt: skip
            with socket.create_connection(("127.0.0.1", p.port), timeout=5) as s:
                assert tcp_rpc(s, 1, bytes.fromhex("0600050007")) == mbap(1, b"\x86\x01")
                assert tcp_rpc(s, 2, bytes.fromhex("0300050001")) == mbap(2, b"\x03\x02\x00\x05")
            out, _ = p.stop()
    assert "Guard: refused 0x06 write R5 on unit 1 (read-only)" in out
    bus_requests = [ln for ln in out.splitlines() if "[u1]" in ln and "Receive from" in ln]
    assert len(bus_requests) == 1 and " 03 00 05 00 01" in bus_requests[0]  # the write never


def test_tcp_to_rtu_a_refusal_pipelined_after_a_read_comes_after_its_answer() -> None:
    """A read and a write ``--read-only`` refuses, in one segment: the read's answer
    comes from the bus first, then the refusal (every ADU its answer, in order),
    each whole."""
    with pty_pair() as (bus_proxy, bus_slave), server("rtu", bus_slave):
        with proxy("--upstream-serial", bus_proxy, "--listen", "127.0.0.1:0",
                   "--read-only") as p:  # fmt: skip
            with socket.create_connection(("127.0.0.1", p.port), timeout=5) as s:
                s.sendall(
                    mbap(1, bytes.fromhex("0300050001")) + mbap(2, bytes.fromhex("0600050007"))
                )
                want = mbap(1, b"\x03\x02\x00\x05") + mbap(2, b"\x86\x01")
                got = b""
                while len(got) < len(want):
                    part = s.recv(4096)
                    assert part, got
                    got += part
            p.stop()
    assert got == want


# --------------------------------------------------------------------------- RTU <-> RTU


def test_rtu_to_rtu_byte_identical_and_a_refused_write_gets_an_rtu_exception() -> None:
    with pty_pair() as (master, master_side), pty_pair() as (bus_proxy, bus_slave):
        with server("rtu", bus_slave):
            rtu_session(bus_proxy)  # the writes done once
            direct = rtu_session(bus_proxy)
            with proxy("--listen-serial", master_side, "--upstream-serial", bus_proxy) as p:
                through = rtu_session(master)
                raw = RawMaster(master)
                try:  # without a guard the write reaches the slave, and its echo comes back
                    passed = raw.ask(1, bytes.fromhex("0600050007"), wait=0.5)
                finally:
                    raw.close()
                out, err = p.stop()
        # with a guard: the refusal as the slave would send it, CRC included
        with proxy("--listen-serial", master_side, "--upstream-serial", bus_proxy,
                   "--deny-write", "hr:5") as p:  # fmt: skip
            raw = RawMaster(master)
            try:
                refused = raw.ask(1, bytes.fromhex("0600050007"), wait=0.5)
            finally:
                raw.close()
            out2, _ = p.stop()
    assert len(direct) == 10
    assert through == direct  # whole RTU frames: unit id, PDU and CRC
    assert passed == encode_rtu(1, bytes.fromhex("0600050007"))
    assert refused == encode_rtu(1, b"\x86\x01")
    assert "Guard: refused 0x06 write R5 on unit 1 (deny-write hr:5)" in out2
    # both buses reached the hub: the master's and the slave's, 10 answers each
    assert out.count("03 14 00 00 00 01") >= 2, out
    assert "requests 11, responses 11" in err


def test_rtu_to_rtu_silent_slave_means_silence_for_the_master() -> None:
    with pty_pair() as (master, master_side), pty_pair() as (bus_proxy, _nobody):
        with proxy("--listen-serial", master_side, "--upstream-serial", bus_proxy,
                   "--timeout", "0.3") as p:  # fmt: skip
            raw = RawMaster(master)
            try:
                assert raw.ask(1, bytes.fromhex("0300000002"), wait=0.8) == b""
            finally:
                raw.close()
            out, err = p.stop()
    assert "silence, as from an RTU slave" in out
    assert "left unanswered (silence for 0x0A/0x0B) 1" in err
    assert "0x0B 0" in err  # nothing was sent to the master


# --------------------------------------------------------------------------- RTU -> TCP


def test_rtu_to_tcp_answers_as_the_tcp_server_does() -> None:
    port = free_port()
    with server("tcp", str(port)), pty_pair() as (master, master_side):
        tcp_session(port)  # the writes done once
        direct = tcp_session(port)
        with proxy("--listen-serial", master_side, "--upstream", f"127.0.0.1:{port}") as p:
            through = rtu_session(master)
            out, err = p.stop()
    assert len(direct) == 10 and len(through) == 10
    assert pdus_rtu(through) == pdus_tcp(direct)
    # the RTU bus and the Modbus/TCP side both reached the hub
    assert "Client 127.0.0.1" not in out
    assert re.search(r"\[u1 t\d+\]  03 00 00 00 0A", out), out  # the TCP side
    assert re.search(r"\[u1\]  03 00 00 00 0A", out), out  # the master's bus
    assert "requests 10, responses 10" in err


def test_rtu_to_tcp_upstream_down_silence_and_read_only() -> None:
    port = free_port()  # nothing listens there
    with pty_pair() as (master, master_side):
        with proxy("--listen-serial", master_side, "--upstream", f"127.0.0.1:{port}",
                   "--read-only", "--timeout", "0.5") as p:  # fmt: skip
            raw = RawMaster(master)
            try:
                assert raw.ask(1, bytes.fromhex("0300000002"), wait=0.8) == b""
                assert raw.ask(1, bytes.fromhex("10000A000102002A"), wait=0.4) == encode_rtu(
                    1, b"\x90\x01"
                )
            finally:
                raw.close()
            out, err = p.stop()
    assert "upstream unavailable; silence, as from an RTU slave" in out
    assert "Guard: refused 0x10 write R10 on unit 1 (read-only)" in out
    assert "left unanswered (silence for 0x0A/0x0B) 1" in err


def test_serial_usage_and_a_missing_port() -> None:
    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "mbmon", "proxy", *args],
            capture_output=True,
            text=True,
            env=ENV,
            timeout=30,
        )

    both = run("--upstream", "127.0.0.1:502", "--upstream-serial", "/dev/null")
    assert both.returncode == 2 and "give the upstream once" in both.stderr
    none = run("--listen", "1502")
    assert none.returncode == 2 and "give the upstream once" in none.stderr
    two = run("--upstream", "127.0.0.1:502", "--listen", "1502", "--listen-serial", "/dev/x")
    assert two.returncode == 2 and "--listen-serial" in two.stderr
    missing = run("--upstream-serial", "/nonexistent/ttyX", "--listen", "127.0.0.1:0")
    assert missing.returncode == 1
    assert "cannot open serial port /nonexistent/ttyX: No such file" in missing.stderr
    assert "Traceback" not in missing.stderr


def test_live_monitor_with_an_rtu_master_shows_its_bus_and_the_silences() -> None:
    """In process: the engine with an RTU front (upstream down), the hub and the live
    monitor on a recording console."""
    from mbmon.commands.common import Figures
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.monitor.app import render_text
    from mbmon.monitor.feed import MonitorFeed
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.proxy.config import ProxyConfig
    from mbmon.proxy.engine import ProxyEngine
    from mbmon.proxy.observer import Observer
    from mbmon.proxy.runner import ProxyThread
    from mbmon.proxy.serial import rtu_front
    from mbmon.sources.serial import SerialSettings

    with pty_pair() as (master, master_side):
        monitor = MonitorFeed(View(robot=master_side))
        hub = Hub(Pipeline(None, PipelineConfig(timeout=2.0, baudrate=BAUD)))
        hub.add_listener(monitor)
        config = ProxyConfig(upstream_host="127.0.0.1", upstream_port=free_port(), timeout=0.3)
        engine = ProxyEngine(
            config,
            Observer(hub.put, hub.new_stream),
            submit=hub.submit,
            front=rtu_front(master_side, SerialSettings(BAUD)),
        )
        hub.add_listener(Figures(monitor, engine.figures))
        thread = ProxyThread(engine, on_exit=hub.stop)
        assert thread.start() == (master_side, 0)
        runner = threading.Thread(target=hub.run, daemon=True)
        runner.start()
        raw = RawMaster(master)
        try:
            assert raw.ask(1, bytes.fromhex("0300640002"), wait=0.6) == b""
            time.sleep(0.3)
            figures = engine.figures()
        finally:
            raw.close()
            thread.stop()
            thread.join(5)
            runner.join(5)
            hub.close()
        monitor.on_tick(time.time())
        text = render_text(monitor, (250, 40))
    assert figures["clients"] == 1 and figures["left silent"] == 1
    assert figures["upstream"].startswith("unavailable (connection refused)")
    assert "left silent 1" in text and "0x0A answers 0" in text
    # the master's request on its bus, with the labels of the slave the proxy plays
    assert re.search(r"Receive from client  \[u1\]  03 00 64 00 02 ", text), text
    assert "upstream unavailable; silence, as from an RTU slave" in text


# --------------------------------------------------------------------------- libmodbus's bytes


class ScriptedSlave:
    """An RTU slave on a pty that answers each expected request with the answer
    recorded for it (or with nothing), in the order of a recorded session."""

    def __init__(self, device: str, script: list[tuple[bytes, bytes | None]]) -> None:
        from mbmon.sources.serial import SerialSettings, open_port

        self.port = open_port(device, SerialSettings(BAUD))
        self.fd = self.port.fileno()
        self.script = script
        self.done = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set() and self.done < len(self.script):
            if not select.select([self.fd], [], [], 0.05)[0]:
                continue
            buf += os.read(self.fd, 512)
            request, answer = self.script[self.done]
            if buf.endswith(request):
                buf = b""
                self.done += 1
                if answer is not None:
                    time.sleep(0.002)
                    os.write(self.fd, answer)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.port.close()


def test_rtu_to_rtu_libmodbus_session_every_answer_through() -> None:
    # libmodbus's RTU unit-test session, bad requests included (quantity 0 with a
    # byte count that disagrees, CRC correct): each request reaches the slave and
    # its answer the master, byte for byte; a request nobody answers gets silence
    from rtu_corpus import BAD_REQUESTS, session

    frames = session()
    script: list[tuple[bytes, bytes | None]] = []
    for i, (who, raw) in enumerate(frames):
        if who != ">":
            continue
        nxt = frames[i + 1] if i + 1 < len(frames) else None
        answer = nxt[1] if nxt is not None and nxt[0] == "<" else None
        script.append((raw, answer))
    assert all(req in dict(script) for req, _ in BAD_REQUESTS)
    with pty_pair() as (master, master_side), pty_pair() as (bus_proxy, bus_slave):
        slave = ScriptedSlave(bus_slave, script)
        try:
            with proxy("--listen-serial", master_side, "--upstream-serial", bus_proxy,
                       "--timeout", "0.3") as p:  # fmt: skip
                from mbmon.sources.serial import SerialSettings, open_port

                port = open_port(master, SerialSettings(BAUD))
                fd = port.fileno()
                got: list[tuple[bytes, bytes, bytes]] = []
                try:
                    for request, answer in script:
                        # the master hears its own slave only: an answer from
                        # another unit (libmodbus's server does that once) is
                        # dropped by the proxy, as is a broadcast's
                        want = answer if answer and answer[0] == request[0] else b""
                        os.write(fd, request)
                        back = b""
                        deadline = time.monotonic() + (2.0 if want else 0.5)
                        while time.monotonic() < deadline and (not want or len(back) < len(want)):
                            if select.select([fd], [], [], 0.05)[0]:
                                back += os.read(fd, 512)
                        got.append((request, want, back))
                        time.sleep(0.01)
                finally:
                    port.close()
                out, _ = p.stop()
        finally:
            slave.close()
    wrong = [(r.hex(" "), w.hex(" "), b.hex(" ")) for r, w, b in got if w != b]
    assert wrong == []
    assert slave.done == len(script)  # every request reached the slave
    for req, answer in BAD_REQUESTS[:2]:
        assert (req, answer, answer) in got
    assert "malformed" in out  # the quantity-0 writes are shown as such
