"""SimServer's answers on raw sockets and ptys: every ADU answered, in order, with its own code.

Pipelined requests (several ADUs in one TCP segment, as a proxy sharing one
upstream among many clients writes them) each get their answer, in the order
they came, however the stream is cut into segments. A function code the robot
does not implement is answered exception 01 with that function code, whether
pymodbus knows the code or not; a Table 10 request whose lengths disagree is
answered exception 03. Byte tables: requests and answers as they are on the wire.
"""

from __future__ import annotations

import itertools
import shutil
import socket
import struct
import time
from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mbmon.protocol.crc import add_crc
from mbmon.protocol.mbap import encode_adu
from mbmon.sim.server import SimServer

UNIT = 1


@pytest.fixture(scope="module")
def server() -> Iterator[SimServer]:
    with SimServer(unit=UNIT) as s:
        yield s


def recv_adus(sock: socket.socket, count: int, timeout: float = 10.0) -> list[bytes]:
    """Read exactly ``count`` MBAP ADUs (or what came before ``timeout``)."""
    buf = b""
    out: list[bytes] = []
    deadline = time.monotonic() + timeout
    while len(out) < count and time.monotonic() < deadline:
        while len(buf) >= 6 and len(buf) >= 6 + struct.unpack(">H", buf[4:6])[0]:
            end = 6 + struct.unpack(">H", buf[4:6])[0]
            out.append(buf[:end])
            buf = buf[end:]
        if len(out) >= count:
            break
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            data = sock.recv(65536)
        except TimeoutError:
            break
        if not data:
            break
        buf += data
    return out


def read_ir(tid: int, address: int, count: int = 1) -> bytes:
    return encode_adu(tid, UNIT, struct.pack(">BHH", 4, address, count))


def test_twenty_pipelined_requests_in_one_segment_get_twenty_answers_in_order(
    server: SimServer,
) -> None:
    with socket.create_connection((server.host, server.port)) as sock:
        sock.sendall(b"".join(read_ir(tid, 100) for tid in range(20)))
        answers = recv_adus(sock, 20)
    assert [struct.unpack(">H", a[:2])[0] for a in answers] == list(range(20))
    assert all(a[6:9] == bytes([UNIT, 4, 2]) for a in answers)


@pytest.mark.parametrize("count", [23, 100, 1000])
def test_segments_longer_than_one_adu_limit_are_answered_whole(
    server: SimServer, count: int
) -> None:
    # pymodbus drops a read longer than 264 bytes (23 reads of 12 bytes) unseen
    with socket.create_connection((server.host, server.port)) as sock:
        sock.sendall(b"".join(read_ir(tid, 100) for tid in range(count)))
        answers = recv_adus(sock, count, timeout=60)
    assert [struct.unpack(">H", a[:2])[0] for a in answers] == list(range(count))


def test_a_write_then_a_read_in_one_segment_are_run_in_that_order(server: SimServer) -> None:
    write = encode_adu(1, UNIT, struct.pack(">BHH", 6, 100, 42))  # speed 42 %
    back = encode_adu(2, UNIT, struct.pack(">BHH", 6, 100, 100))
    with socket.create_connection((server.host, server.port)) as sock:
        sock.sendall(write + read_ir(2, 100) + back + read_ir(3, 100))
        answers = recv_adus(sock, 4)
    assert answers[0] == write
    assert answers[1] == bytes.fromhex("0002 0000 0005 01 04 02 002A")
    assert answers[2] == back
    assert answers[3] == bytes.fromhex("0003 0000 0005 01 04 02 0064")


def test_a_request_split_after_another_is_not_lost_when_the_first_is_answered(
    server: SimServer,
) -> None:
    # the first segment holds one ADU and the head of the next: answering the first
    # must not drop the head (pymodbus's send clears its receive buffer)
    two = read_ir(7, 100) + read_ir(8, 101)
    with socket.create_connection((server.host, server.port)) as sock:
        sock.sendall(two[:16])
        first = recv_adus(sock, 1)
        sock.sendall(two[16:])
        second = recv_adus(sock, 1)
    assert [a[:2] for a in first + second] == [b"\x00\x07", b"\x00\x08"]


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(cuts=st.lists(st.integers(min_value=1, max_value=12 * 10 - 1), max_size=8, unique=True))
def test_any_segmentation_of_ten_requests_gets_ten_answers_in_order(
    server: SimServer, cuts: list[int]
) -> None:
    stream = b"".join(read_ir(100 + i, 100 + i % 3) for i in range(10))
    bounds = [0, *sorted(cuts), len(stream)]
    with socket.create_connection((server.host, server.port)) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for a, b in itertools.pairwise(bounds):
            sock.sendall(stream[a:b])
            time.sleep(0.001)
        answers = recv_adus(sock, 10)
    assert [struct.unpack(">H", a[:2])[0] for a in answers] == [100 + i for i in range(10)]


#: (request PDU, answer PDU): what the robot does not implement, and malformed Table 10 requests.
EXCEPTIONS: list[tuple[str, str, str]] = [
    ("Read File Record, valid", "14 07 06 0001 0000 000A", "94 01"),
    ("Read File Record, two sub-requests", "14 0E 06 0001 0000 0001 06 0002 0000 0001", "94 01"),
    ("Write File Record", "15 09 06 0001 0000 0001 1234", "95 01"),
    ("Read Exception Status", "07", "87 01"),
    ("Diagnostics, return query data", "08 0000 A537", "88 01"),
    ("Diagnostics, force listen only", "08 0004 0000", "88 01"),
    ("Get Comm Event Counter", "0B", "8B 01"),
    ("Report Server ID", "11", "91 01"),
    ("Mask Write Register", "16 00C9 FFFF 0000", "96 01"),
    ("Read/Write Multiple registers", "17 00C8 0001 00C9 0001 02 0000", "97 01"),
    ("Read FIFO Queue", "18 0000", "98 01"),
    ("Read Device Identification", "2B 0E 01 00", "AB 01"),
    ("user-defined code 0x41, no data", "41", "C1 01"),
    ("user-defined code 0x41 with data", "41 00 01", "C1 01"),
    ("user-defined code 0x64", "64 01 02 03", "E4 01"),
    ("function code 0", "00", "80 01"),
    ("Read Holding Registers, truncated", "03 0000", "83 03"),
    ("Write Multiple registers, byte count disagrees", "10 0064 0001 04 0023", "90 03"),
]


@pytest.mark.parametrize(("request_pdu", "answer_pdu"), [c[1:] for c in EXCEPTIONS],
                         ids=[c[0] for c in EXCEPTIONS])  # fmt: skip
def test_requests_the_robot_does_not_serve_are_answered_with_their_own_function_code(
    server: SimServer, request_pdu: str, answer_pdu: str
) -> None:
    with socket.create_connection((server.host, server.port)) as sock:
        sock.sendall(encode_adu(0x55, UNIT, bytes.fromhex(request_pdu)) + read_ir(0x56, 100))
        answers = recv_adus(sock, 2)
    assert answers[0] == encode_adu(0x55, UNIT, bytes.fromhex(answer_pdu))
    assert answers[1][:2] == b"\x00\x56"  # and the stream goes on


def rtu(hexbytes: str) -> bytes:
    return add_crc(bytes.fromhex(hexbytes))


@pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")
def test_read_file_record_over_rtu_is_answered_94_01_decodable_or_not() -> None:
    import os
    import termios
    import tty

    from socat_ptys import pty_pair

    with pty_pair() as (server_pty, client_pty):
        server = SimServer(serial=server_pty, baudrate=115200, unit=UNIT)
        server.start()
        fd = os.open(client_pty, os.O_RDWR | os.O_NOCTTY)
        try:
            tty.setraw(fd)
            termios.tcflush(fd, termios.TCIOFLUSH)
            got = b""
            for request, answer in [
                (rtu("01 14 07 06 0001 0000 000A"), rtu("01 94 01")),
                # two sub-requests: pymodbus cannot decode it, the sim still answers it
                (rtu("01 14 0E 06 0001 0000 0001 06 0002 0000 0001"), rtu("01 94 01")),
                # codes pymodbus does not know at all
                (rtu("01 41"), rtu("01 C1 01")),
                (rtu("00 41"), b""),  # a broadcast: never answered
                (rtu("02 41"), b""),  # another device's
                (rtu("01 64 01 02 03"), rtu("01 E4 01")),
                (rtu("01 04 0064 0001"), rtu("01 04 02 0064")),
                (rtu("01 04 0064 0001"), rtu("01 04 02 0064")),
            ]:
                os.write(fd, request)
                got = b""
                deadline = time.monotonic() + (5 if answer else 0.3)
                while (not answer or len(got) < len(answer)) and time.monotonic() < deadline:
                    os.set_blocking(fd, False)
                    try:
                        got += os.read(fd, 256)
                    except BlockingIOError:
                        time.sleep(0.01)
                assert got == answer
        finally:
            os.close(fd)
            server.stop()


def test_a_hundred_clients_through_a_shared_upstream_proxy_get_every_answer() -> None:
    """The proxy's --share-upstream writes many clients' requests to the sim in one
    segment: every one is answered, none with a gateway exception."""
    import asyncio
    import os
    import subprocess
    import sys
    from pathlib import Path

    clients, each = 100, 50
    seen = {False: 0, True: 0}

    def tap(sending: bool, data: bytes) -> None:
        seen[sending] += 1

    async def client(port: int, cid: int, bad: list[bytes]) -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        for i in range(each):
            tid = cid * each + i
            writer.write(read_ir(tid, 100))
            head = await reader.readexactly(6)
            body = await reader.readexactly(struct.unpack(">H", head[4:6])[0])
            if head[:2] != tid.to_bytes(2, "big") or body[1] & 0x80:
                bad.append(head + body)
        writer.close()

    async def everyone(port: int) -> list[bytes]:
        bad: list[bytes] = []
        await asyncio.wait_for(
            asyncio.gather(*(client(port, c, bad) for c in range(clients))), timeout=120
        )
        return bad

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        listen = probe.getsockname()[1]
    root = Path(__file__).resolve().parents[2]
    with SimServer(unit=UNIT, on_packet=tap) as sim:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "proxy", "--upstream", f"{sim.host}:{sim.port}",
             "--listen", f"127.0.0.1:{listen}", "--share-upstream", "-q"],
            cwd=root, env={**os.environ, "PYTHONPATH": str(root)},
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            deadline = time.monotonic() + 30
            while True:
                try:
                    socket.create_connection(("127.0.0.1", listen), timeout=1).close()
                    break
                except OSError:
                    assert proc.poll() is None and time.monotonic() < deadline, "no proxy"
                    time.sleep(0.1)
            bad = asyncio.run(everyone(listen))
        finally:
            proc.terminate()
            proc.communicate(timeout=30)
    assert bad == []
    assert seen == {False: clients * each, True: clients * each}
