"""The proxy never invents or hides an answer: ``mbmon proxy`` as a real subprocess
between raw clients and a scripted upstream on 127.0.0.1 (an asyncio server in the
test's own loop, so each test says exactly what the upstream sends and when).

* per client, whatever the upstream sends goes to the client unchanged, an answer
  with an unknown transaction id too, and a request the upstream answered that way
  gets no gateway exception (libmodbus's server answers tid 0x27 with tid 0);
* with ``--share-upstream`` such an answer cannot be routed: dropped, and said so;
* once the proxy answered a request itself (0x0B), nothing the upstream sends for
  it reaches the client: 0 wrong answers in 10,000 with in-order and out-of-order
  upstreams, reused and incrementing transaction ids, delays around the timeout;
* the upstream's bytes go on as they arrive (an answer sent a byte every 5 ms).
"""

from __future__ import annotations

import asyncio
import json
import random
import struct
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from pathlib import Path

import pytest

from tests.proxy.test_proxy_e2e import Proxy

Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]
Answer = Callable[[asyncio.StreamWriter, bytes], Awaitable[None]]


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


async def read_adu(reader: asyncio.StreamReader) -> bytes:
    head = await reader.readexactly(7)
    return head + await reader.readexactly(struct.unpack(">H", head[4:6])[0] - 1)


def answering(answer: Answer, *, at_once: bool = False) -> Handler:
    """An upstream's connection handler: ``answer(writer, request)`` for each request
    ADU the connection brings, one after the other, or (``at_once``) each on its own
    as soon as it is read (answers overtake). When the connection ends, so do the
    answers still on their way."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        tasks: set[asyncio.Future[None]] = set()
        try:
            while True:
                req = await read_adu(reader)
                if not at_once:
                    await answer(writer, req)
                    continue
                task = asyncio.ensure_future(answer(writer, req))
                tasks.add(task)
                task.add_done_callback(tasks.discard)
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            for task in tasks:
                task.cancel()
            writer.close()

    return handle


async def no_answer(writer: asyncio.StreamWriter, req: bytes) -> None:
    """An upstream that reads every request and never answers."""


async def start_upstream(handle: Handler) -> tuple[asyncio.Server, int]:
    server = await asyncio.start_server(handle, "127.0.0.1", 0, backlog=1024)
    return server, int(server.sockets[0].getsockname()[1])


@asynccontextmanager
async def through_proxy(handle: Handler, tmp: Path, *args: str) -> AsyncIterator[Proxy]:
    """A scripted upstream (``handle``) on 127.0.0.1 and ``mbmon proxy --quiet *args``
    in front of it (``p.port``; the upstream's is ``p.upstream_port``). On leaving,
    the proxy is stopped as by Ctrl-C and must exit 0 (its stderr, the summary, is
    then ``p.summary``), and the upstream is closed."""
    server, port = await start_upstream(handle)
    try:
        p = await asyncio.to_thread(Proxy, port, "--quiet", *args, tmp=tmp)
        try:
            yield p
        finally:
            await asyncio.to_thread(p.stop)
            assert p.returncode == 0, p.summary
    finally:
        server.close()


async def silence(reader: asyncio.StreamReader, seconds: float) -> bytes:
    """What arrives within ``seconds`` (b"" when nothing does)."""
    try:
        return await asyncio.wait_for(reader.read(100), seconds)
    except TimeoutError:
        return b""


def log_notices(path: Path) -> list[dict]:
    out = []
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        if rec.get("kind") == "event":
            out.append(rec)
    return out


# --------------------------------------------------------------------------- unknown tid

#: libmodbus's unit-test-server, asked for R0x171, answers with transaction id 0
#: whatever the request's (``UT_REGISTERS_ADDRESS_INVALID_TID_OR_SLAVE``).
LIBMODBUS_BAD_TID_REQUEST = bytes.fromhex("00 27 00 00 00 06 FF 03 01 71 00 01")
LIBMODBUS_BAD_TID_ANSWER = bytes.fromhex("00 00 00 00 00 05 FF 03 02 00 00")
#: the client's next transaction, and its proper answer
NEXT_REQUEST = bytes.fromhex("00 2D 00 00 00 06 FF 03 01 60 00 01")
NEXT_ANSWER = bytes.fromhex("00 2D 00 00 00 05 FF 03 02 12 34")


def bad_tid_upstream(bad_tid: int = 0) -> Handler:
    """Answers R0x171 with transaction id ``bad_tid`` (libmodbus's: 0) after 50 ms,
    R0x172 after 300 ms, the rest at once; each request on its own."""

    async def answer(writer: asyncio.StreamWriter, req: bytes) -> None:
        if req[8:10] == b"\x01\x71":
            await asyncio.sleep(0.05)
            writer.write(bad_tid.to_bytes(2, "big") + LIBMODBUS_BAD_TID_ANSWER[2:])
            return
        if req[8:10] == b"\x01\x72":
            await asyncio.sleep(0.3)
        writer.write(req[:2] + NEXT_ANSWER[2:])

    return answering(answer, at_once=True)


@pytest.mark.parametrize("shared", [False, True], ids=["per-client", "share-upstream"])
def test_unknown_tid_answer_is_forwarded_unchanged_and_no_0B_follows(
    tmp_path: Path, shared: bool
) -> None:
    """libmodbus's sequence: the answer with tid 0 reaches the client as sent (libmodbus
    rejects it itself), and no made-up 0x0B lands in the next transaction. Shared, the
    one request in flight is what it answers (the first request uses up the shared
    link's id 0, so the answer's id is really unknown)."""
    extra = ["--share-upstream"] if shared else []

    async def main() -> str:
        async with through_proxy(
            bad_tid_upstream(), tmp_path, "--timeout", "0.3", "-w", "bad-tid.jsonl", *extra
        ) as p:
            reader, writer = await asyncio.open_connection("127.0.0.1", p.port)
            writer.write(NEXT_REQUEST)
            assert await asyncio.wait_for(read_adu(reader), 5) == NEXT_ANSWER
            writer.write(LIBMODBUS_BAD_TID_REQUEST)
            assert await asyncio.wait_for(read_adu(reader), 5) == LIBMODBUS_BAD_TID_ANSWER
            # the upstream answered: no made-up 0x0B, not at the timeout, not later
            assert await silence(reader, 0.9) == b""
            writer.write(NEXT_REQUEST)
            assert await asyncio.wait_for(read_adu(reader), 5) == NEXT_ANSWER
            assert await silence(reader, 0.5) == b""
            writer.close()
        return p.summary

    err = asyncio.run(main())
    assert "0x0B 0" in err
    assert "forwarded with an unknown tid 1" in err
    notices = [n["info"].get("message", "") for n in log_notices(tmp_path / "bad-tid.jsonl")]
    assert any("tid 0 matches no request's tid: forwarded unchanged" in m for m in notices)


def test_unknown_tid_answer_is_dropped_and_said_so_when_shared_and_ambiguous(
    tmp_path: Path,
) -> None:
    """Shared, answers are routed by tid: with two clients' requests in flight an
    answer with an id never given cannot be routed: dropped and logged, its request
    (never answered) gets 0x0B at the timeout, the other client its own answer."""

    async def main() -> str:
        async with through_proxy(
            bad_tid_upstream(0xBEEF),
            tmp_path,
            "--timeout",
            "0.5",
            "--share-upstream",
            "-w",
            "shared.jsonl",
        ) as p:
            r1, w1 = await asyncio.open_connection("127.0.0.1", p.port)
            r2, w2 = await asyncio.open_connection("127.0.0.1", p.port)
            w2.write(bytes.fromhex("00 05 00 00 00 06 FF 03 01 72 00 01"))  # 300 ms
            await asyncio.sleep(0.05)
            w1.write(LIBMODBUS_BAD_TID_REQUEST)
            got1, got2 = await asyncio.gather(
                asyncio.wait_for(read_adu(r1), 5), asyncio.wait_for(read_adu(r2), 5)
            )
            assert got1 == bytes.fromhex("00 27 00 00 00 03 FF 83 0B")
            assert got2 == b"\x00\x05" + NEXT_ANSWER[2:]
            w1.close()
            w2.close()
        return p.summary

    err = asyncio.run(main())
    assert "unmatched answers dropped 1" in err
    notices = [n["info"].get("message", "") for n in log_notices(tmp_path / "shared.jsonl")]
    assert any(
        "unknown tid 48879 dropped: the shared connection routes answers by tid "
        "(2 requests in flight)" in m
        for m in notices
    ), notices


# --------------------------------------------------------------------------- late answers

TIMEOUT = 0.05


def _value(address: int) -> int:
    return (address * 7 + 3) & 0xFFFF


def make_upstream(order: str, rng: random.Random) -> Handler:
    """An upstream that answers a read of one register at A with ``_value(A)`` after a
    random delay of 0..2 timeouts: ``in-order`` one request after the other per
    connection, ``out-of-order`` each request on its own (answers overtake)."""

    async def answer(writer: asyncio.StreamWriter, req: bytes, delay: float) -> None:
        await asyncio.sleep(delay)
        address = (req[8] << 8) | req[9]
        if not writer.is_closing():
            writer.write(
                mbap((req[0] << 8) | req[1], req[6], struct.pack(">BBH", 3, 2, _value(address)))
            )

    def after_a_delay(writer: asyncio.StreamWriter, req: bytes) -> Awaitable[None]:
        return answer(writer, req, rng.uniform(0, 2 * TIMEOUT))  # drawn as it is read

    return answering(after_a_delay, at_once=order != "in-order")


class Tally:
    def __init__(self) -> None:
        self.answers = 0
        self.gateway = 0
        self.wrong: list[str] = []


async def client(
    port: int, n: int, tids: str, depth: int, rng: random.Random, tally: Tally
) -> None:
    """``n`` reads of one register each, ``depth`` in flight at once; every answer must
    be its own request's value, or a gateway exception; nothing more may come after."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    in_flight: dict[int, int] = {}  # tid -> address
    sent = 0
    tid = 1
    last_address = -1
    while sent < n or in_flight:
        while sent < n and len(in_flight) < depth:
            if tids == "incrementing":
                tid = (tid + 1) & 0xFFFF
            address = rng.randrange(0, 60000)
            if address == last_address:
                address += 1
            last_address = address
            in_flight[tid] = address
            writer.write(mbap(tid, 1, struct.pack(">BHH", 3, address, 1)))
            sent += 1
        try:
            got = await asyncio.wait_for(read_adu(reader), 10)
        except (TimeoutError, asyncio.IncompleteReadError) as exc:
            tally.wrong.append(f"no answer: {exc!r}")
            break
        rtid = (got[0] << 8) | got[1]
        address = in_flight.pop(rtid, None)
        if address is None:
            tally.wrong.append(f"answer to no request in flight: {got.hex(' ')}")
            continue
        tally.answers += 1
        if got[7] == 0x83:
            # made by the proxy: no answer in time (0x0B), or the renewed upstream
            # connection not up within the timeout (0x0A): never the upstream's
            if got[8] not in (0x0A, 0x0B):
                tally.wrong.append(f"exception {got.hex(' ')}")
            tally.gateway += 1
        elif got[7:9] != b"\x03\x02" or (got[9] << 8 | got[10]) != _value(address):
            tally.wrong.append(f"R{address} answered {got.hex(' ')}")
    extra = await silence(reader, 4 * TIMEOUT)
    if extra:
        tally.wrong.append(f"after the last answer: {extra.hex(' ')}")
    writer.close()


@pytest.mark.parametrize(
    ("order", "tids", "depth"),
    [
        ("in-order", "reused", 1),
        ("in-order", "incrementing", 3),
        ("out-of-order", "reused", 1),
        ("out-of-order", "incrementing", 3),
    ],
)
def test_late_answers_never_reach_a_later_request(
    tmp_path: Path, order: str, tids: str, depth: int
) -> None:
    """2,500 requests per case (10,000 over the four) of 50 clients, answers random
    0..100 ms late around a 50 ms timeout: each answer is its own request's or 0x0B."""
    rng = random.Random(f"{order}-{tids}")
    tally = Tally()

    async def main() -> str:
        async with through_proxy(
            make_upstream(order, rng), tmp_path, "--timeout", str(TIMEOUT)
        ) as p:
            await asyncio.gather(
                *(client(p.port, 50, tids, depth, random.Random(i), tally) for i in range(50))
            )
        return p.summary

    start = time.monotonic()
    err = asyncio.run(main())
    assert tally.wrong == [], f"{len(tally.wrong)} wrong: {tally.wrong[:5]}"
    assert tally.answers == 2500
    # the case is real: many late answers were made 0x0B, many answers came in time
    assert tally.gateway > 200 and tally.answers - tally.gateway > 20, (tally.gateway, err)
    assert "late answers dropped 0" not in err
    assert time.monotonic() - start < 120


def test_late_answers_never_reach_a_later_request_shared(tmp_path: Path) -> None:
    rng = random.Random("shared")
    tally = Tally()

    async def main() -> str:
        async with through_proxy(
            make_upstream("out-of-order", rng),
            tmp_path,
            "--timeout",
            str(TIMEOUT),
            "--share-upstream",
        ) as p:
            await asyncio.gather(
                *(client(p.port, 40, "reused", 1, random.Random(i), tally) for i in range(50))
            )
        return p.summary

    asyncio.run(main())
    assert tally.wrong == [], f"{len(tally.wrong)} wrong: {tally.wrong[:5]}"
    assert tally.answers == 2000
    assert tally.gateway > 100


# --------------------------------------------------------------------------- as they arrive

#: libmodbus's server, asked for R0x173, sends its answer one byte every 5 ms.
SLOW_REQUEST = bytes.fromhex("00 1C 00 00 00 06 FF 03 01 73 00 01")
SLOW_ANSWER = bytes.fromhex("00 1C 00 00 00 05 FF 03 02 00 00")


async def write_slowly(writer: asyncio.StreamWriter, data: bytes, gap: float) -> None:
    """``data`` one byte every ``gap`` seconds."""
    for i in range(len(data)):
        writer.write(data[i : i + 1])
        await writer.drain()
        await asyncio.sleep(gap)


def byte_by_byte(gap: float = 0.005) -> Handler:
    """Answers every request with :data:`SLOW_ANSWER` (the request's id), one byte
    every ``gap`` seconds, one request after the other."""

    async def answer(writer: asyncio.StreamWriter, req: bytes) -> None:
        await write_slowly(writer, req[:2] + SLOW_ANSWER[2:], gap)

    return answering(answer)


@pytest.mark.parametrize("shared", [False, True], ids=["per-client", "share-upstream"])
def test_answer_bytes_are_forwarded_as_they_arrive(tmp_path: Path, shared: bool) -> None:
    """The client reads the first bytes of an answer while the upstream is still
    sending the rest (not all at once after the last byte); shared, from the byte
    that completes the transaction id on (its own id put back)."""
    extra = ["--share-upstream"] if shared else []

    async def main() -> list[float]:
        async with through_proxy(byte_by_byte(), tmp_path, "-w", "slow.jsonl", *extra) as p:
            reader, writer = await asyncio.open_connection("127.0.0.1", p.port)
            writer.write(SLOW_REQUEST)
            got = b""
            times = []
            while len(got) < len(SLOW_ANSWER):
                part = await asyncio.wait_for(reader.read(100), 5)
                assert part
                got += part
                times.append(time.monotonic())
            assert got == SLOW_ANSWER
            writer.close()
        return times

    times = asyncio.run(main())
    # 11 bytes 5 ms apart: the reads are spread over the ~50 ms the upstream took
    assert len(times) >= 4, times
    assert times[-1] - times[0] > 0.025
    # the log still holds the one whole answer, paired with its request
    records = [json.loads(line) for line in (tmp_path / "slow.jsonl").read_text().splitlines()]
    assert [r["kind"] for r in records if r["kind"] in ("request", "response")] == [
        "request",
        "response",
    ]


# --------------------------------------------------------------------------- who answered


def test_gateway_exception_is_logged_as_the_proxys_own_answer(tmp_path: Path) -> None:
    """A 0x0B the proxy made has the proxy as its source in the JSON, in the MCAP log
    and in the pcap ``export`` makes of it: never the server's endpoint."""
    import subprocess
    import sys

    from tests.proxy.test_proxy_e2e import ENV

    async def main() -> tuple[int, int]:
        async with through_proxy(
            answering(no_answer), tmp_path, "--timeout", "0.2", "-w", "gw.jsonl", "-w", "gw.mcap"
        ) as p:
            reader, writer = await asyncio.open_connection("127.0.0.1", p.port)
            writer.write(NEXT_REQUEST)
            got = await asyncio.wait_for(read_adu(reader), 5)
            assert got == bytes.fromhex("00 2D 00 00 00 03 FF 83 0B")
            writer.close()
        return p.upstream_port, p.port

    upstream_port, proxy_port = asyncio.run(main())
    proxy_at = f"127.0.0.1:{proxy_port}"

    def exceptions(lines: list[str]) -> list[dict]:
        recs = [json.loads(line) for line in lines if line.strip()]
        return [r for r in recs if r.get("kind") == "exception"]

    (live,) = exceptions((tmp_path / "gw.jsonl").read_text().splitlines())
    assert live["src"] == proxy_at and live["exception_code"] == 0x0B
    out = subprocess.run(
        [sys.executable, "-m", "mbmon", "export", "gw.mcap", "-o", "gw.pcap", "--keep-port"],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    out = subprocess.run(
        [sys.executable, "-m", "mbmon", "replay", "gw.mcap", "--json"],
        cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    got = exceptions(out.stdout.splitlines())
    assert [(r["src"], r["exception_code"]) for r in got] == [(proxy_at, 0x0B)]
    # the pcap: the 0x0B's TCP segment comes from the proxy's port
    ports = {
        payload: (sport, dport) for sport, dport, payload in tcp_payloads(tmp_path / "gw.pcap")
    }
    assert ports[bytes.fromhex("00 2D 00 00 00 03 FF 83 0B")][0] == proxy_port
    assert ports[NEXT_REQUEST][1] == upstream_port  # the request went to the server


def tcp_payloads(path: Path) -> list[tuple[int, int, bytes]]:
    """(source port, destination port, payload) of each TCP segment with data of a
    classic Ethernet/IPv4 pcap (what ``export`` writes for a TCP log)."""
    data = path.read_bytes()
    assert struct.unpack("<I", data[:4])[0] == 0xA1B2C3D4
    assert struct.unpack("<I", data[20:24])[0] == 1  # Ethernet
    out = []
    pos = 24
    while pos + 16 <= len(data):
        incl = struct.unpack("<I", data[pos + 8 : pos + 12])[0]
        frame = data[pos + 16 : pos + 16 + incl]
        pos += 16 + incl
        if frame[12:14] != b"\x08\x00":
            continue
        ip = frame[14:]
        ihl = (ip[0] & 0x0F) * 4
        total = struct.unpack(">H", ip[2:4])[0]
        tcp = ip[ihl:total]
        sport, dport = struct.unpack(">HH", tcp[:4])
        payload = tcp[(tcp[12] >> 4) * 4 :]
        if payload:
            out.append((sport, dport, payload))
    return out


def test_unresolvable_upstream_warns_at_start_and_keeps_running(tmp_path: Path) -> None:
    """``--upstream nosuchhost.invalid:502``: a warning right after the start-up line
    (and in the log), then the proxy runs on and answers 0x0A (the host may come)."""
    import re
    import signal
    import socket
    import subprocess
    import sys

    from tests.proxy.test_proxy_e2e import ENV

    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "proxy", "--upstream", "nosuchhost.invalid:502",
         "--listen", "127.0.0.1:0", "--quiet", "-w", "nh.jsonl"],
        cwd=tmp_path, env=ENV, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stderr is not None
        first = proc.stderr.readline()
        m = re.search(r"listening on 127\.0\.0\.1:(\d+)", first)
        assert m, first
        second = proc.stderr.readline()
        assert "warning: upstream host 'nosuchhost.invalid' does not resolve" in second
        assert "0x0A" in second
        with socket.create_connection(("127.0.0.1", int(m.group(1))), timeout=10) as s:
            s.sendall(NEXT_REQUEST)
            got = b""
            while len(got) < 9:
                part = s.recv(100)
                assert part
                got += part
        assert got == bytes.fromhex("00 2D 00 00 00 03 FF 83 0A")
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGINT)
        rest = proc.communicate(timeout=20)[1]
    assert proc.returncode == 0, rest
    assert "does not resolve" in (tmp_path / "nh.jsonl").read_text()


def test_renewed_connection_drains_and_says_which_late_answer_it_dropped(
    tmp_path: Path,
) -> None:
    """Per client: A (tid 7) gets 0x0B at the timeout; B, sent before that on the same
    upstream connection, still gets its own answer from it; A's late answer is
    dropped and logged with its bytes; C, reusing tid 7 on the renewed connection,
    gets its own answer, never A's."""
    # by register address: A's late answer (0.6 s) comes while C is in flight
    delays = {0x0A: 0.6, 0x0B: 0.2, 0x0C: 0.25}

    async def delayed(writer: asyncio.StreamWriter, req: bytes) -> None:
        address = (req[8] << 8) | req[9]
        await asyncio.sleep(delays[address])
        writer.write(
            req[:2] + bytes.fromhex("00 00 00 05") + req[6:8] + b"\x02\x00" + bytes([address])
        )

    def read(tid: int, address: int) -> bytes:
        return mbap(tid, 1, struct.pack(">BHH", 3, address, 1))

    def answer(tid: int, address: int) -> bytes:
        return mbap(tid, 1, bytes([3, 2, 0, address]))

    async def main() -> str:
        async with through_proxy(
            answering(delayed, at_once=True), tmp_path, "--timeout", "0.4", "-w", "renew.jsonl"
        ) as p:
            reader, writer = await asyncio.open_connection("127.0.0.1", p.port)
            writer.write(read(7, 0x0A))  # A: 0x0B at 0.4 s, answered at 0.6 s
            await asyncio.sleep(0.3)
            writer.write(read(8, 0x0B))  # B: answered at 0.5 s, on the old connection
            got = await asyncio.wait_for(read_adu(reader), 5)
            assert got == bytes.fromhex("00 07 00 00 00 03 01 83 0B")
            got = await asyncio.wait_for(read_adu(reader), 5)
            assert got == answer(8, 0x0B)
            writer.write(read(7, 0x0C))  # C: tid 7 again, in flight when A's answer comes
            got = await asyncio.wait_for(read_adu(reader), 5)
            assert got == answer(7, 0x0C)
            assert await silence(reader, 0.5) == b""  # A's late answer never comes
            writer.close()
        return p.summary

    err = asyncio.run(main())
    assert "late answers dropped 1" in err
    assert "renewed after a gateway timeout 1" in err
    notices = [n["info"] for n in log_notices(tmp_path / "renew.jsonl")]
    (late,) = [n for n in notices if "late answer" in n.get("message", "")]
    assert late["tid"] == 7
    assert late["raw"] == answer(7, 0x0A).hex(" ").upper()


def test_rtu_master_gets_a_whole_frame_of_an_answer_sent_byte_by_byte(tmp_path: Path) -> None:
    """An RTU master (``--listen-serial``) needs whole answers to make RTU frames: an
    upstream answer that comes a byte at a time reaches it as one frame, CRC right."""
    import os
    import select
    import shutil
    import signal
    import subprocess
    import sys
    import threading

    from socat_ptys import pty_pair

    from mbmon.protocol.rtu import encode_rtu
    from tests.proxy.test_proxy_e2e import ENV

    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (the serial side needs a pty pair)")
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    ports: list[int] = []

    def run() -> None:
        asyncio.set_event_loop(loop)
        server, port = loop.run_until_complete(start_upstream(byte_by_byte()))
        ports.append(port)
        ready.set()
        loop.run_forever()
        server.close()

    threading.Thread(target=run, daemon=True).start()
    ready.wait(10)
    try:
        with pty_pair() as (master, master_side):
            proc = subprocess.Popen(
                [sys.executable, "-m", "mbmon", "proxy", "--listen-serial", master_side,
                 "--upstream", f"127.0.0.1:{ports[0]}", "--quiet"],
                cwd=tmp_path, env=ENV, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip
            try:
                assert proc.stderr is not None
                assert "listening on" in proc.stderr.readline()
                fd = os.open(master, os.O_RDWR | os.O_NOCTTY)
                try:
                    time.sleep(0.3)
                    os.write(fd, encode_rtu(0xFF, bytes.fromhex("03 01 73 00 01")))
                    want = encode_rtu(0xFF, bytes.fromhex("03 02 00 00"))
                    got = b""
                    deadline = time.monotonic() + 5
                    while len(got) < len(want) and time.monotonic() < deadline:
                        if select.select([fd], [], [], 0.2)[0]:
                            got += os.read(fd, 100)
                    assert got == want
                finally:
                    os.close(fd)
            finally:
                proc.send_signal(signal.SIGINT)
                err = proc.communicate(timeout=20)[1]
            assert proc.returncode == 0, err
            assert "requests 1, responses 1" in err
    finally:
        loop.call_soon_threadsafe(loop.stop)
