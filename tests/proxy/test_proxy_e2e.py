"""``mbmon proxy`` end to end: the command runs as a real subprocess between real
sockets on 127.0.0.1 — a pymodbus server and client, a small scripted upstream
(a separate process: normal, silent, half an answer, late answers) and raw
socket clients (garbage, slowloris, a client that never reads)."""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}

# --------------------------------------------------------------------------- peers

#: A scripted Modbus/TCP server, run as ``python -c FAKE PORT MODE LOG``. It prints
#: ``port N`` once listening and writes ``fc XX`` to the file LOG for every request.
#: Registers read as their own address + unit (03/04), coils as address parity,
#: writes are echoed (05/06/0F/10 answered as the spec says), other codes get
#: exception 01. Modes: ``normal``; ``silent`` (reads, never answers); ``reset``
#: (first connection: reset (RST) on the first request);
#: ``half`` (first connection: half of each answer, then nothing); ``late``
#: (the first request is answered after 1.5 s, the rest at once).
FAKE = r"""
import asyncio, os, struct, sys
port, mode = int(sys.argv[1]), sys.argv[2]
log = os.open(sys.argv[3], os.O_WRONLY | os.O_CREAT | os.O_APPEND)
conns = [0]
late_done = [False]

def answer(tid, unit, pdu):
    fc = pdu[0]
    if fc in (3, 4):
        addr, count = struct.unpack(">HH", pdu[1:5])
        body = bytes([fc, 2 * count]) + b"".join(
            struct.pack(">H", (addr + i + unit) & 0xFFFF) for i in range(count))
    elif fc in (1, 2):
        addr, count = struct.unpack(">HH", pdu[1:5])
        bits = [(addr + i) & 1 for i in range(count)]
        data = bytearray((count + 7) // 8)
        for i, b in enumerate(bits):
            data[i // 8] |= b << (i % 8)
        body = bytes([fc, len(data)]) + bytes(data)
    elif fc in (5, 6):
        body = pdu[:5]
    elif fc in (15, 16):
        body = pdu[:5]
    else:
        body = bytes([fc | 0x80, 1])
    return struct.pack(">HHHB", tid, 0, len(body) + 1, unit) + body

async def handle(reader, writer):
    conns[0] += 1
    first_conn = conns[0] == 1
    try:
        while True:
            head = await reader.readexactly(7)
            tid, _pid, length, unit = struct.unpack(">HHHB", head)
            pdu = await reader.readexactly(length - 1)
            os.write(log, b"fc %02X\n" % pdu[0])
            if mode == "silent":
                continue
            if mode == "reset" and first_conn:
                import socket
                sock = writer.get_extra_info("socket")
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                writer.transport.abort()
                return
            adu = answer(tid, unit, pdu)
            if mode == "half" and first_conn:
                writer.write(adu[: len(adu) // 2])
                continue
            if mode == "late" and not late_done[0]:
                late_done[0] = True
                await asyncio.sleep(1.5)
            writer.write(adu)
    except (asyncio.IncompleteReadError, ConnectionError):
        pass
    finally:
        writer.close()

async def main():
    server = await asyncio.start_server(handle, "127.0.0.1", port, reuse_address=True)
    print("port", server.sockets[0].getsockname()[1], flush=True)
    async with server:
        await server.serve_forever()

asyncio.run(main())
"""

PYMODBUS_SERVER = r"""
import asyncio, sys, logging
logging.disable(logging.CRITICAL)
import warnings; warnings.simplefilter("ignore")
from pymodbus.datastore import (ModbusDeviceContext, ModbusSequentialDataBlock,
                                ModbusServerContext)
from pymodbus.server import StartAsyncTcpServer
def block(): return ModbusSequentialDataBlock(1, list(range(1000)))
dev = ModbusDeviceContext(di=block(), co=block(), hr=block(), ir=block())
ctx = ModbusServerContext(devices=dev, single=True)
asyncio.run(StartAsyncTcpServer(context=ctx, address=("127.0.0.1", int(sys.argv[1]))))
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_port(port: int, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.05)
    raise AssertionError(f"nothing listens on port {port}")


class Fake:
    """The scripted upstream in its own process; ``fcs()`` lists what it received."""

    def __init__(self, mode: str = "normal", port: int = 0) -> None:
        fd, self.log = tempfile.mkstemp(prefix="fake-upstream-")
        os.close(fd)
        self.proc = subprocess.Popen(
            [sys.executable, "-c", FAKE, str(port), mode, self.log],
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        self.port = int(line.split()[1])

    def fcs(self) -> list[int]:
        """The function code of every request received, in order."""
        lines = Path(self.log).read_text().split()
        return [int(x, 16) for x in lines[1::2]]

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
            if self.proc.stdout is not None:
                self.proc.stdout.close()
        if os.path.exists(self.log):
            os.unlink(self.log)


@contextmanager
def fake(mode: str = "normal", port: int = 0) -> Iterator[Fake]:
    f = Fake(mode, port)
    try:
        yield f
    finally:
        f.kill()


@contextmanager
def pymodbus_server(port: int | None = None) -> Iterator[int]:
    port = port or free_port()
    proc = subprocess.Popen(
        [sys.executable, "-c", PYMODBUS_SERVER, str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_port(port)
        yield port
    finally:
        proc.kill()
        proc.wait()


class Proxy:
    """``python -m mbmon proxy`` as a subprocess; ``stop()`` ends it like Ctrl-C."""

    def __init__(
        self, upstream_port: int, *args: str, tmp: Path, env: dict[str, str] | None = None
    ) -> None:
        self.upstream_port = upstream_port
        #: what the proxy wrote on stderr, once :meth:`stop` ran (the summary)
        self.summary = ""
        self.out_path = tmp / f"proxy-{upstream_port}-{time.monotonic_ns()}.out"
        self._out = self.out_path.open("w")
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "mbmon",
                "proxy",
                "--upstream",
                f"127.0.0.1:{upstream_port}",
                "--listen",
                "127.0.0.1:0",
                *args,
            ],
            stdout=self._out,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV if env is None else env,
            cwd=tmp,
        )
        assert self.proc.stderr is not None
        self.err: list[str] = []
        line = self.proc.stderr.readline()
        self.err.append(line)
        m = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
        assert m, f"proxy did not start: {line}{self.proc.stderr.read()}"
        self.port = int(m.group(1))
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.returncode: int | None = None

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.err.append(line)

    def stop(self) -> tuple[str, str]:
        """Stop as Ctrl-C does; stdout and stderr."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        self.returncode = self.proc.wait(timeout=20)
        self._reader.join(5)
        self._out.close()
        self.summary = "".join(self.err)
        return self.out_path.read_text(), self.summary


@contextmanager
def proxy(
    upstream_port: int, *args: str, tmp: Path, env: dict[str, str] | None = None
) -> Iterator[Proxy]:
    p = Proxy(upstream_port, *args, tmp=tmp, env=env)
    try:
        yield p
    finally:
        if p.proc.poll() is None:
            p.stop()


# --------------------------------------------------------------------------- a raw client


def adu(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def read_adu(sock: socket.socket) -> bytes:
    head = recv_exactly(sock, 7)
    length = struct.unpack(">H", head[4:6])[0]
    return head + recv_exactly(sock, length - 1)


def recv_exactly(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        part = sock.recv(n - len(buf))
        if not part:
            raise ConnectionError(f"closed after {len(buf)} of {n} bytes")
        buf += part
    return buf


def connect(port: int, timeout: float = 5.0) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=timeout)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def rpc(sock: socket.socket, tid: int, pdu: bytes, unit: int = 1) -> bytes:
    sock.sendall(adu(tid, unit, pdu))
    return read_adu(sock)


def read_hr(address: int, count: int) -> bytes:
    return struct.pack(">BHH", 3, address, count)


def expected_hr(tid: int, unit: int, address: int, count: int) -> bytes:
    body = bytes([3, 2 * count]) + b"".join(
        struct.pack(">H", (address + i + unit) & 0xFFFF) for i in range(count)
    )
    return adu(tid, unit, body)


def exception(tid: int, fc: int, code: int, unit: int = 1) -> bytes:
    return adu(tid, unit, bytes([fc | 0x80, code]))


def mcap_events(path: Path) -> list[dict]:
    from mbmon.io.mcap.reader import open_log

    with open_log(path) as log:
        return [m.json() for m in log.messages(["/mbmon/events"])]


# --------------------------------------------------------------------------- transparency


def _pymodbus_session(port: int) -> list[bytes]:
    """Every function code pymodbus's client offers that the server answers; the
    raw response bytes, in order."""
    from pymodbus.client import ModbusTcpClient
    from pymodbus.pdu.diag_message import ReturnQueryDataRequest
    from pymodbus.pdu.file_message import FileRecord

    received: list[bytes] = []

    def trace(sending: bool, data: bytes) -> bytes:
        if not sending:
            received.append(bytes(data))
        return data

    client = ModbusTcpClient("127.0.0.1", port=port, trace_packet=trace, timeout=3, retries=0)
    assert client.connect()
    try:
        client.read_coils(0, count=19)
        client.read_discrete_inputs(3, count=7)
        client.read_holding_registers(0, count=10)
        client.read_input_registers(5, count=3)
        client.write_coil(2, True)
        client.write_register(7, 0x1234)
        client.write_coils(8, [True, False, True])
        client.write_registers(20, [1, 2, 3, 4])
        client.mask_write_register(address=7, and_mask=0xF2F2, or_mask=0x2525)
        client.readwrite_registers(read_address=20, read_count=4, write_address=30, values=[9, 8])
        client.read_holding_registers(60000, count=2)  # exception 02
        client.execute(False, ReturnQueryDataRequest(message=b"\x12\x34"))
        client.read_fifo_queue(address=1)
        client.read_device_information()
        client.report_device_id()
        client.read_exception_status()
        client.diag_get_comm_event_counter()
        client.diag_get_comm_event_log()
        client.diag_read_bus_message_count()
        client.write_file_record([FileRecord(file_number=1, record_number=0,
                                             record_data=b"\x00\x01\x00\x02")])  # fmt: skip
        for i in range(20):
            client.read_holding_registers(i, count=1 + i)
    finally:
        client.close()
    return received


#: Function codes the pymodbus session above must have been answered with (its
#: answers' codes, exception bit cleared): the comparison covers each of them.
PYMODBUS_CODES = {0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0B, 0x0C, 0x0F,
                  0x10, 0x11, 0x15, 0x16, 0x17, 0x18, 0x2B}  # fmt: skip

#: A well-formed request for each public code; every other code 1..127 (user-defined,
#: reserved) is sent as ``fc 00 00 00 01``: the proxy frames by the MBAP length only.
RAW_REQUESTS = {
    0x14: "14 07 06 00 01 00 00 00 02",
    0x15: "15 0B 06 00 01 00 00 00 02 00 01 00 02",
    0x0F: "0F 00 08 00 03 01 05",
    0x10: "10 00 14 00 02 04 00 01 00 02",
    0x16: "16 00 07 F2 F2 25 25",
    0x17: "17 00 14 00 04 00 1E 00 02 04 00 09 00 08",
    0x2B: "2B 0E 01 00",
    0x08: "08 00 00 12 34",
    0x18: "18 00 01",
    0x07: "07", 0x0B: "0B", 0x0C: "0C", 0x11: "11",
}  # fmt: skip


def _raw_session(port: int) -> list[bytes]:
    """One request of every function code 1..127 from a raw socket (two rounds:
    the writes' effects are in place for the second); the raw answers, in order."""
    answers: list[bytes] = []
    with connect(port) as sock:
        for _round in range(2):
            for fc in range(1, 128):
                pdu = bytes.fromhex(RAW_REQUESTS.get(fc, f"{fc:02X} 00 00 00 01"))
                answers.append(rpc(sock, fc, pdu))
    return answers


def test_transparency_pymodbus_byte_identical(tmp_path: Path) -> None:
    with pymodbus_server() as port:
        _pymodbus_session(port)  # the writes' effects are in place before comparing
        _raw_session(port)
        direct = _pymodbus_session(port)
        raw_direct = _raw_session(port)
        with proxy(port, "--quiet", "-w", "t.mcap", tmp=tmp_path) as p:
            through = _pymodbus_session(p.port)
            raw_through = _raw_session(p.port)
            _out, err = p.stop()
    assert len(direct) >= 35
    assert {answer[7] & 0x7F for answer in direct} >= PYMODBUS_CODES
    assert through == direct
    assert len(raw_direct) == 2 * 127
    assert raw_through == raw_direct
    assert p.returncode == 0
    assert "exceptions made by the proxy 0" in err
    assert f"requests {len(direct) + len(raw_direct)}, responses" in err


# --------------------------------------------------------------------------- concurrency


async def _client(port: int, index: int, n: int, errors: list[str]) -> int:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    unit = 1 + index % 7
    ok = 0
    try:
        for k in range(n):
            tid = (k + index % 3) & 0xFFFF  # many clients use the same ids at once
            address = (index * 37 + k) % 1000
            count = 1 + (index + k) % 10
            writer.write(adu(tid, unit, read_hr(address, count)))
            head = await reader.readexactly(7)
            body = await reader.readexactly(struct.unpack(">H", head[4:6])[0] - 1)
            if head + body != expected_hr(tid, unit, address, count):
                errors.append(f"client {index} req {k}: {(head + body).hex()}")
            else:
                ok += 1
    finally:
        writer.close()
    return ok


async def _many(port: int, clients: int, n: int) -> tuple[int, list[str]]:
    errors: list[str] = []
    oks = await asyncio.gather(*(_client(port, i, n, errors) for i in range(clients)))
    return sum(oks), errors


@pytest.mark.parametrize("shared", [False, True], ids=["per-client", "share-upstream"])
def test_100_concurrent_clients_no_crosstalk(tmp_path: Path, shared: bool) -> None:
    clients, n = 100, 200
    extra = ["--share-upstream"] if shared else []
    with fake() as up, proxy(up.port, "--quiet", *extra, tmp=tmp_path) as p:
        ok, errors = asyncio.run(_many(p.port, clients, n))
        _out, err = p.stop()
    assert errors == []
    assert ok == clients * n
    assert f"requests {clients * n}, responses {clients * n}" in err
    assert "exceptions made by the proxy 0" in err
    assert "upstream connections 1 " in err if shared else f"upstream connections {clients} " in err


# --------------------------------------------------------------------------- failures


def test_upstream_down_at_start_then_back(tmp_path: Path) -> None:
    port = free_port()
    with proxy(port, "--quiet", "--timeout", "1", "-w", "f.mcap", tmp=tmp_path) as p:
        sock = connect(p.port)
        start = time.monotonic()
        for tid in range(1, 4):
            assert rpc(sock, tid, read_hr(0, 2)) == exception(tid, 3, 0x0A)
        assert time.monotonic() - start < 1.0
        with fake(port=port):
            deadline = time.monotonic() + 5
            tid = 10
            while True:  # the same connection recovers once the backoff allows a try
                tid += 1
                answer = rpc(sock, tid, read_hr(4, 2))
                if answer == expected_hr(tid, 1, 4, 2):
                    break
                assert answer == exception(tid, 3, 0x0A)
                assert time.monotonic() < deadline, "the proxy never reconnected"
                time.sleep(0.1)
        sock.close()
        _out, err = p.stop()
    assert "0x0A" in err
    messages = [e["info"].get("message", "") for e in mcap_events(tmp_path / "f.mcap")]
    assert any("unavailable" in m for m in messages)
    assert any("is back" in m for m in messages)


def test_upstream_killed_mid_run_and_restarted(tmp_path: Path) -> None:
    up = Fake()
    port = up.port
    try:
        with proxy(port, "--quiet", "--timeout", "1", tmp=tmp_path) as p:
            sock = connect(p.port)
            assert rpc(sock, 1, read_hr(0, 3)) == expected_hr(1, 1, 0, 3)
            up.kill()
            start = time.monotonic()
            answer = rpc(sock, 2, read_hr(0, 3))
            assert answer in (exception(2, 3, 0x0A), exception(2, 3, 0x0B))
            assert time.monotonic() - start < 1.5
            up = Fake(port=port)
            deadline = time.monotonic() + 5
            tid = 3
            while rpc(sock, tid, read_hr(1, 1)) != expected_hr(tid, 1, 1, 1):
                assert time.monotonic() < deadline, "no recovery"
                tid += 1
                time.sleep(0.1)
            sock.close()
            _out, err = p.stop()
    finally:
        up.kill()
    assert "upstream connections 2" in err or "upstream connections 3" in err


def test_upstream_silent_answers_0B_within_timeout(tmp_path: Path) -> None:
    with fake("silent") as up, proxy(up.port, "--quiet", "--timeout", "0.5", tmp=tmp_path) as p:
        sock = connect(p.port)
        for tid in (7, 8):  # the connection stays usable
            start = time.monotonic()
            assert rpc(sock, tid, read_hr(0, 1)) == exception(tid, 3, 0x0B)
            assert 0.4 < time.monotonic() - start < 1.5
        sock.close()
        _out, err = p.stop()
    assert "0x0B 2" in err


@pytest.mark.parametrize("shared", [False, True], ids=["per-client", "share-upstream"])
def test_late_answer_is_dropped_never_delivered(tmp_path: Path, shared: bool) -> None:
    extra = ["--share-upstream"] if shared else []
    with (
        fake("late") as up,
        proxy(
            up.port, "--quiet", "--timeout", "0.5", "-w", "late.jsonl", *extra, tmp=tmp_path
        ) as p,
    ):
        sock = connect(p.port)
        assert rpc(sock, 1, read_hr(0, 1)) == exception(1, 3, 0x0B)
        time.sleep(1.3)  # the late answer to tid 1 arrives and must be dropped
        assert rpc(sock, 2, read_hr(5, 2)) == expected_hr(2, 1, 5, 2)
        sock.settimeout(0.3)
        with pytest.raises(TimeoutError):
            sock.recv(100)  # nothing else ever comes
        sock.close()
        _out, err = p.stop()
    assert "late answers dropped 1" in err
    log = (tmp_path / "late.jsonl").read_text()
    # the upstream id: the client's own, or the first remapped one (0) when shared
    assert f"late answer from upstream (tid {0 if shared else 1}) dropped" in log


@pytest.mark.parametrize("shared", [False, True], ids=["per-client", "share-upstream"])
def test_half_answer_is_forwarded_then_the_client_dropped(tmp_path: Path, shared: bool) -> None:
    """The upstream's bytes go on as they come (shared: once the transaction id is
    there): the client has the first half of the answer at once; no exception can
    follow it, so when the rest never comes (one more timeout) the client is
    dropped, and its next connection works (on a fresh upstream connection)."""
    extra = ["--share-upstream"] if shared else []
    with (
        fake("half") as up,
        proxy(up.port, "--quiet", "--timeout", "0.5", *extra, tmp=tmp_path) as p,
    ):
        sock = connect(p.port)
        whole = expected_hr(1, 1, 0, 4)
        start = time.monotonic()
        sock.sendall(adu(1, 1, read_hr(0, 4)))
        assert recv_exactly(sock, len(whole) // 2) == whole[: len(whole) // 2]
        assert time.monotonic() - start < 0.4  # before the timeout: not held back
        sock.settimeout(5)
        try:
            assert sock.recv(100) == b""  # dropped, nothing else came
        except ConnectionResetError:
            pass  # dropped with a reset
        assert 0.8 < time.monotonic() - start < 3
        sock.close()
        sock = connect(p.port)
        deadline = time.monotonic() + 5
        tid = 2
        while rpc(sock, tid, read_hr(0, 4)) != expected_hr(tid, 1, 0, 4):
            assert time.monotonic() < deadline
            tid += 1
        sock.close()
        _out, err = p.stop()
    assert "dropped 1" in err
    assert "upstream connections 2" in err


# --------------------------------------------------------------------------- guard

WRITES = {
    0x05: bytes.fromhex("05 00 10 FF 00"),
    0x06: bytes.fromhex("06 00 10 00 2A"),
    0x0F: bytes.fromhex("0F 00 10 00 03 01 05"),
    0x10: bytes.fromhex("10 00 10 00 02 04 00 01 00 02"),
    0x15: bytes.fromhex("15 09 06 00 04 00 07 00 01 12 34"),
    0x16: bytes.fromhex("16 00 10 00 F2 00 25"),
    0x17: bytes.fromhex("17 00 00 00 02 00 10 00 01 02 00 2A"),
}


def test_read_only_blocks_every_write_and_audits_in_mcap(tmp_path: Path) -> None:
    with fake() as up, proxy(up.port, "--quiet", "--read-only", "-w", "g.mcap", tmp=tmp_path) as p:
        sock = connect(p.port)
        for tid, (fc, pdu) in enumerate(sorted(WRITES.items()), start=1):
            assert rpc(sock, tid, pdu, unit=3) == exception(tid, fc, 0x01, unit=3)
        assert rpc(sock, 99, read_hr(0, 2)) == expected_hr(99, 1, 0, 2)
        sock.close()
        time.sleep(0.2)
        _out, err = p.stop()
        received = up.fcs()
    assert received == [0x03]  # no write ever reached the upstream
    assert "guard refusals 7" in err
    guards = [e for e in mcap_events(tmp_path / "g.mcap") if e.get("event") == "guard"]
    assert len(guards) == 7, guards
    infos = [g["info"] for g in guards]
    assert sorted(i["fc"] for i in infos) == sorted(WRITES)
    for info in infos:
        assert info["rule"] == "read-only"
        assert info["unit"] == 3
        assert info["client"].startswith("127.0.0.1:")
        assert {"message", "address", "count"} <= set(info)
    by_fc = {i["fc"]: i for i in infos}
    assert (by_fc[0x10]["address"], by_fc[0x10]["count"]) == (16, 2)
    assert (by_fc[0x17]["address"], by_fc[0x17]["count"]) == (16, 1)


def test_read_only_allow_list_malformed_writes_and_allow_fc_end_to_end(tmp_path: Path) -> None:
    """--read-only lets only known reads through: 08/01 (restart communications),
    08/04 (force listen-only) and user-defined 65 are refused and audited, a write
    whose quantity and byte count disagree is refused as malformed although
    --allow-write covers its address; --allow-fc 8/1 opens exactly 08/01."""
    args = ["--quiet", "--read-only", "--allow-write", "hr:200-251", "--allow-fc", "8/1",
            "--guard-exception", "4", "-w", "ro.jsonl"]  # fmt: skip
    cases = [
        (bytes.fromhex("08 00 01 00 00"), True),  # opened by --allow-fc 8/1
        (bytes.fromhex("08 00 04 00 00"), False),
        (bytes.fromhex("08 00 00 12 34"), True),  # Return Query Data: a known read
        (bytes.fromhex("41 00 01"), False),
        (bytes.fromhex("10 00 FB 00 01 04 00 01 00 02"), False),  # qty 1, 2 values
        (bytes.fromhex("10 00 FB 00 01 02 00 01"), True),
        (bytes.fromhex("0F 00 10 00 08 02 FF FF"), False),  # not in --allow-write anyway
    ]
    with fake() as up, proxy(up.port, *args, tmp=tmp_path) as p:
        sock = connect(p.port)
        for tid, (pdu, passes) in enumerate(cases, start=1):
            got = rpc(sock, tid, pdu)
            if passes:
                assert got[7:9] != bytes([pdu[0] | 0x80, 0x04]), pdu.hex(" ")
            else:
                assert got == exception(tid, pdu[0], 0x04), pdu.hex(" ")
        sock.close()
        time.sleep(0.2)
        _out, err = p.stop()
        received = up.fcs()
    assert received == [0x08, 0x08, 0x10]
    assert "guard refusals 4" in err
    records = [json.loads(line) for line in (tmp_path / "ro.jsonl").read_text().splitlines()]
    guards = [r["info"] for r in records if r.get("event") == "guard"]
    assert [(g["fc"], g["rule"]) for g in guards] == [
        (0x08, "read-only"),
        (0x41, "read-only"),
        (0x10, "malformed"),
        (0x0F, "malformed"),
    ]
    assert guards[0]["sub_function"] == 4
    assert "byte count 4 but 1 registers need 2" in guards[2]["reason"]


def test_allow_and_deny_edges_end_to_end(tmp_path: Path) -> None:
    args = ["--quiet", "--allow-write", "hr:100-110", "--deny-write", "hr:105",
            "--guard-exception", "4"]  # fmt: skip
    cases = [(99, False), (100, True), (104, True), (105, False), (110, True), (111, False)]
    with fake() as up, proxy(up.port, *args, tmp=tmp_path) as p:
        sock = connect(p.port)
        for tid, (address, allowed) in enumerate(cases, start=1):
            pdu = struct.pack(">BHH", 6, address, 1)
            want = adu(tid, 1, pdu) if allowed else exception(tid, 6, 0x04)
            assert rpc(sock, tid, pdu) == want, address
        sock.close()
        _out, err = p.stop()
    assert "guard refusals 3" in err


def test_allow_from_refuses_other_clients(tmp_path: Path) -> None:
    with fake() as up, proxy(up.port, "--allow-from", "10.0.0.0/8", tmp=tmp_path) as p:
        sock = connect(p.port)
        with pytest.raises((ConnectionError, OSError)):
            rpc(sock, 1, read_hr(0, 1))
        sock.close()
        out, err = p.stop()
    assert "refused client 127.0.0.1:" in out
    assert "refused 1" in err


# --------------------------------------------------------------------------- bad clients


def test_garbage_client_dropped_others_unaffected(tmp_path: Path) -> None:
    with fake() as up, proxy(up.port, "-w", "bad.jsonl", tmp=tmp_path) as p:
        good = connect(p.port)
        assert rpc(good, 1, read_hr(0, 1)) == expected_hr(1, 1, 0, 1)
        bad = connect(p.port)
        bad.sendall(b"GET / HTTP/1.1\r\nHost: robot\r\n\r\n")
        with pytest.raises((ConnectionError, OSError)):
            if not bad.recv(100):
                raise ConnectionError("closed")
        for tid in range(2, 12):
            assert rpc(good, tid, read_hr(tid, 2)) == expected_hr(tid, 1, tid, 2)
        good.close()
        bad.close()
        out, err = p.stop()
    assert "dropped: client sent bytes that are not Modbus/TCP (bad MBAP header" in out
    # the upstream is the robot by default: the robot's own Modbus Monitor labels
    assert "Receive from client  [u1 t1]  03 00 00 00 01" in out
    assert "Send to client  [u1 t1]  03 02 00 01" in out
    assert "clients 2 (refused 0, dropped 1)" in err


def test_slowloris_and_non_reader_dropped_while_100_clients_work(tmp_path: Path) -> None:
    with fake() as up, proxy(up.port, "--timeout", "1", "-w", "stuck.jsonl", "--quiet",
                             tmp=tmp_path) as p:  # fmt: skip
        # a client that never reads: a tiny receive buffer fills at once
        lazy = socket.socket()
        lazy.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        lazy.connect(("127.0.0.1", p.port))
        lazy.setblocking(False)
        batch = b"".join(adu(i, 1, read_hr(0, 125)) for i in range(50))

        def pump() -> None:  # 1000 requests a second until the proxy stops reading
            deadline = time.monotonic() + 6
            pending = b""
            while time.monotonic() < deadline:
                pending = pending or batch
                try:
                    pending = pending[lazy.send(pending) :]
                except BlockingIOError:
                    pass
                except OSError:
                    return
                time.sleep(0.05)

        slow = connect(p.port)
        slow_result: list[str] = []

        def slowloris() -> None:
            try:
                for byte in adu(1, 1, read_hr(0, 1)):
                    slow.sendall(bytes([byte]))
                    time.sleep(1.0)
                slow_result.append("sent everything")
            except OSError as exc:
                slow_result.append(f"cut off: {exc}")

        threads = [threading.Thread(target=pump), threading.Thread(target=slowloris)]
        for t in threads:
            t.start()
        ok, errors = asyncio.run(_many(p.port, 100, 20))
        for t in threads:
            t.join(15)
        lazy.close()
        slow.close()
        _out, err = p.stop()
    assert errors == [] and ok == 2000  # every other client answered right, none dropped
    assert slow_result and slow_result[0].startswith("cut off"), slow_result
    log = (tmp_path / "stuck.jsonl").read_text()
    assert "request incomplete for more than 1 s" in log
    assert "has not read its responses for 1 s" in log
    assert "dropped 2)" in err


def test_summary_and_clean_exit_on_sigterm(tmp_path: Path) -> None:
    with fake() as up:
        p = Proxy(up.port, "--json", tmp=tmp_path)
        sock = connect(p.port)
        assert rpc(sock, 5, read_hr(2, 2)) == expected_hr(5, 1, 2, 2)
        p.proc.send_signal(signal.SIGTERM)
        p.proc.wait(20)
        out, err = p.stop()
        sock.close()
    assert p.returncode == 0
    assert "requests 1, responses 1" in err
    lines = [line for line in out.splitlines() if line.strip()]
    assert any('"kind":"request"' in line.replace(" ", "") for line in lines)
    assert any('"kind":"response"' in line.replace(" ", "") for line in lines)


def test_cannot_listen_is_a_clear_error(tmp_path: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = subprocess.run(
            [
                sys.executable,
                "-m",
                "mbmon",
                "proxy",
                "--upstream",
                "127.0.0.1:1",
                "--listen",
                f"127.0.0.1:{port}",
            ],
            capture_output=True,
            text=True,
            env=ENV,
            timeout=20,
        )
    assert result.returncode == 1
    assert f"cannot listen on 127.0.0.1:{port}" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize(
    "args,words",
    [
        (["--upstream", "robot"], "HOST:PORT"),
        (["--upstream", "robot:x"], "not a port"),
        (["--upstream", "r:502", "--allow-write", "ir:3"], "unknown term"),
        (["--upstream", "r:502", "--allow-from", "nonsense"], "CIDR"),
    ],
)
def test_usage_errors(args: list[str], words: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "mbmon", "proxy", *args],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=20,
    )
    assert result.returncode == 2
    assert words in result.stderr


def test_help_teaches_the_defaults_rules_and_specs() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "mbmon", "proxy", "--help"],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=20,
    )
    assert result.returncode == 0
    text = " ".join(result.stdout.split())
    for words in (
        "default 127.0.0.1:1502, loopback only",
        "0x0A",
        "0x0B",
        "hr:200-251",
        "coil:0-7",
        "unit:2",
        "--deny-write always wins",
        "--share-upstream",
        "--upstream-serial",
        "--listen-serial",
        "the summary still go to stderr",
        "--allow-fc CODE[/SUB]",
        "8/1",
        "only what is known to be a read passes",
        "refused as malformed",
        "that connection is renewed",
    ):
        assert words in text, words  # fmt: skip
    assert "no summary" not in text  # the proxy always prints its summary (a supervisor's)


def test_upstream_reset_answers_0B_at_once_and_reconnects(tmp_path: Path) -> None:
    with (
        fake("reset") as up,
        proxy(up.port, "--quiet", "--timeout", "2", "-w", "rst.jsonl", tmp=tmp_path) as p,
    ):
        sock = connect(p.port)
        start = time.monotonic()
        assert rpc(sock, 1, read_hr(0, 1)) == exception(1, 3, 0x0B)
        assert time.monotonic() - start < 1.0  # not the timeout: the reset is answered now
        assert rpc(sock, 2, read_hr(0, 1)) == expected_hr(2, 1, 0, 1)
        sock.close()
        p.stop()
    log = (tmp_path / "rst.jsonl").read_text()
    assert "closed the connection (RST" in log
    assert "1 requests in flight answered 0x0B" in log


@pytest.mark.parametrize("shared", [False, True], ids=["per-client", "share-upstream"])
def test_client_leaving_mid_request_and_half_close(tmp_path: Path, shared: bool) -> None:
    extra = ["--share-upstream"] if shared else []
    with (
        fake("late") as up,
        proxy(up.port, "--quiet", "--timeout", "3", "-w", "left.jsonl", *extra, tmp=tmp_path) as p,
    ):
        gone = connect(p.port)
        gone.sendall(adu(1, 1, read_hr(0, 1)))  # answered by the upstream 1.5 s later
        time.sleep(0.2)
        gone.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        gone.close()  # a reset: the client is gone for sure
        half = connect(p.port)
        half.sendall(adu(9, 1, read_hr(3, 2)))
        half.shutdown(socket.SHUT_WR)  # half-close: the answer must still come
        assert read_adu(half) == expected_hr(9, 1, 3, 2)
        assert half.recv(10) == b""  # then the proxy closes
        half.close()
        time.sleep(1.6)
        _out, err = p.stop()
    log = (tmp_path / "left.jsonl").read_text()
    assert '"unanswered":1' in log.replace(" ", "")
    assert "client half-closed with 1 requests in flight" in log
    if shared:  # the shared connection lives on: the answer comes, and is dropped
        assert "dropped: its client left" in log
        assert "late answers dropped 1" in err
    else:  # the client's own upstream connection closed with it
        assert "late answers dropped 0" in err


def test_full_disk_log_never_stops_traffic(tmp_path: Path) -> None:
    (tmp_path / "full.jsonl").symlink_to("/dev/full")  # every write: ENOSPC
    with fake() as up, proxy(up.port, "--quiet", "-w", "full.jsonl", tmp=tmp_path) as p:
        sock = connect(p.port)
        for tid in range(300):
            assert rpc(sock, tid, read_hr(tid, 3)) == expected_hr(tid, 1, tid, 3)
            if tid == 150:
                time.sleep(0.6)  # the sink flushes on a tick, fails, and is detached
        sock.close()
        _out, err = p.stop()
    assert "No space left on device" in err
    assert "requests 300, responses 300" in err
    assert p.returncode == 1  # an output failed: the run says so


def test_profile_annotations_and_profile_stored_in_the_log(tmp_path: Path) -> None:
    with fake() as up, proxy(up.port, "--profile", "hrss", "-w", "p.mcap", tmp=tmp_path) as p:
        sock = connect(p.port)
        pdu = bytes.fromhex("10 00 C9 00 03 06 00 6F 00 DE 01 4D")  # R201..R203
        assert rpc(sock, 1, pdu) == adu(1, 1, pdu[:5])
        sock.close()
        out, _err = p.stop()
    assert "R202..R203 parameters = 222 333" in out
    from mbmon.io.mcap.reader import open_log

    with open_log(tmp_path / "p.mcap") as log:
        assert [name for name, _text in log.profiles()]
