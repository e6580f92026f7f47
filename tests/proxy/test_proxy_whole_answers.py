"""The proxy never writes an answer of its own into the middle of another: answers
reach the client whole, and the proxy's own answers (a guard refusal, 0x0B) keep
their requests' places ("every ADU gets its answer, in order").

The upstream's bytes go to the client as they arrive (an answer sent a byte at a
time reaches the client a byte at a time); an answer the proxy makes while one is
half-way to the same client waits until that one is whole, and one made for a
request waits until every earlier request of the client is answered.

Real parts: ``mbmon proxy`` as a subprocess between a raw client socket and an
upstream on 127.0.0.1 that answers one byte every few milliseconds; for the
random interleavings, the engine itself on the test's own loop (many short runs in
seconds). On a serial line (``--listen-serial``) frames are written whole, one
after the other: an answer of the proxy's never enters a frame in flight.
"""

from __future__ import annotations

import asyncio
import random
import struct
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mbmon.model import Chunk, Direction, Event, Stream, Transport
from mbmon.proxy.client import HOLD_LIMIT
from mbmon.proxy.config import ProxyConfig
from mbmon.proxy.engine import ProxyEngine
from mbmon.proxy.guard import Guard
from mbmon.proxy.observer import Observer
from tests.proxy.test_proxy_answers import (
    SLOW_ANSWER,
    SLOW_REQUEST,
    Handler,
    answering,
    mbap,
    start_upstream,
    through_proxy,
    write_slowly,
)

#: R5 = 42, refused by ``--deny-write hr:0-100``; its refusal (exception 01)
WRITE = mbap(0x1D, 0xFF, bytes.fromhex("06 00 05 00 2A"))
REFUSAL = mbap(0x1D, 0xFF, bytes.fromhex("86 01"))
#: a read the upstream below never answers (0x0B at the timeout)
UNANSWERED = mbap(0x1E, 0xFF, bytes.fromhex("03 01 74 00 01"))
GATEWAY_TIMEOUT = mbap(0x1E, 0xFF, bytes.fromhex("83 0B"))


def slow_upstream(gap: float) -> Handler:
    """Answers R0x173 (:data:`SLOW_REQUEST`) one byte every ``gap`` seconds, one
    request after the other, and never answers anything else."""

    async def answer(writer: asyncio.StreamWriter, req: bytes) -> None:
        if req[8:10] == b"\x01\x73":
            await write_slowly(writer, req[:2] + SLOW_ANSWER[2:], gap)

    return answering(answer)


MODES = pytest.mark.parametrize("shared", [False, True], ids=["per-client", "share-upstream"])


def exchange(
    tmp: Path, shared: bool, gap: float, args: list[str], then: bytes, after: int
) -> bytes:
    """What a client receives through ``mbmon proxy *args`` in front of
    :func:`slow_upstream` (``gap``): it sends :data:`SLOW_REQUEST`, and ``then``
    once ``after`` bytes of its answer came (0: in the same segment); the answer's
    bytes and one more answer."""
    extra = ["--share-upstream"] if shared else []

    async def main() -> bytes:
        async with through_proxy(slow_upstream(gap), tmp, *args, *extra) as p:
            reader, writer = await asyncio.open_connection("127.0.0.1", p.port)
            want = len(SLOW_ANSWER) + 9  # and the exception answering ``then``
            if after:
                writer.write(SLOW_REQUEST)
                first = await asyncio.wait_for(reader.readexactly(after), 10)
                writer.write(then)
            else:
                first = b""
                writer.write(SLOW_REQUEST + then)
            rest = await asyncio.wait_for(reader.readexactly(want - len(first)), 10)
            writer.close()
        return first + rest

    return asyncio.run(main())


@MODES
def test_a_refusal_made_while_an_answer_streams_waits_until_it_is_whole(
    tmp_path: Path, shared: bool
) -> None:
    """The client has the first bytes of a read's answer (the upstream sends a byte
    every 5 ms) when it sends a write the guard refuses: the refusal comes after the
    answer's last byte, never inside it."""
    got = exchange(tmp_path, shared, 0.005, ["--deny-write", "hr:0-100"], WRITE, 3)
    assert got == SLOW_ANSWER + REFUSAL


@MODES
def test_a_refused_write_pipelined_after_a_read_is_answered_after_it(
    tmp_path: Path, shared: bool
) -> None:
    """A read and a refused write in one segment: the read's answer (streamed) and
    then the refusal, in the order of the requests."""
    got = exchange(tmp_path, shared, 0.005, ["--deny-write", "hr:0-100"], WRITE, 0)
    assert got == SLOW_ANSWER + REFUSAL


@MODES
def test_a_gateway_timeout_due_while_an_answer_streams_waits_until_it_is_whole(
    tmp_path: Path, shared: bool
) -> None:
    """A read the upstream answers a byte every 30 ms (about 330 ms), then a read it
    never answers, whose 0x0B (timeout 0.2 s) is due while the first answer is
    half-way: the 0x0B follows the answer's last byte."""
    got = exchange(tmp_path, shared, 0.03, ["--timeout", "0.2"], UNANSWERED, 3)
    assert got == SLOW_ANSWER + GATEWAY_TIMEOUT


def test_rtu_frames_are_written_whole_one_after_the_other() -> None:
    """The serial side writes frame by frame (the RTU proxy gives an RTU master whole
    answers, its own refusals too): while the master does not read, the pty fills,
    a frame is left half written and a refusal waits behind it; once the master
    reads, it gets every frame whole, in order, the refusal last."""
    import os
    import select
    import shutil

    from socat_ptys import pty_pair

    from mbmon.protocol.rtu import encode_rtu
    from mbmon.proxy.serial_line import SerialLine
    from mbmon.sources.serial import SerialSettings

    if shutil.which("socat") is None:
        pytest.skip("socat is not installed (the serial side needs a pty pair)")
    answer = encode_rtu(1, bytes([3, 250]) + bytes(range(250)))
    refusal = encode_rtu(1, bytes.fromhex("86 01"))
    frames = 400  # about 100 KB: more than the pty pair holds (about 40 KB)

    async def main(port: str, fd: int) -> bytes:
        loop = asyncio.get_running_loop()
        states: list[tuple[bool, str]] = []
        # 4 Mbaud: the t3.5 silence between frames (1.75 ms) fills the pty in ~0.4 s
        line = SerialLine(
            loop,
            port,
            SerialSettings(baudrate=4_000_000),
            lambda data, ts: None,
            lambda up, why: states.append((up, why)),
        )
        line.open()
        sent: list[bytes] = []
        got = bytearray()
        try:
            for _ in range(frames):
                line.write(answer, lambda frame, ts: sent.append(frame))
            line.write(refusal, lambda frame, ts: sent.append(frame))
            before = -1
            while len(sent) != before:  # until the line waits for the full pty
                before = len(sent)
                await asyncio.sleep(0.2)
            assert len(sent) < frames  # the refusal waits behind a frame in flight
            deadline = loop.time() + 30
            while len(got) < frames * len(answer) + len(refusal) and loop.time() < deadline:
                await asyncio.sleep(0.002)
                while select.select([fd], [], [], 0)[0]:
                    got += os.read(fd, 65536)
        finally:
            line.close()
        assert states == []
        assert len(sent) == frames + 1 and sent[-1] == refusal
        return bytes(got)

    with pty_pair() as (master, proxy_side):
        fd = os.open(master, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            got = asyncio.run(main(proxy_side, fd))
        finally:
            os.close(fd)
    assert got == answer * frames + refusal


# --------------------------------------------------------------------------- interleavings

#: the upstream's behaviour per request, told by the register it reads
STREAMED, SILENT, LATE = 0, 1, 2
KINDS = ("streamed", "silent", "late", "refused")
#: the timeout of the runs below: a late answer comes 1.5 timeouts after its request
PROPERTY_TIMEOUT = 0.25


def _value(address: int) -> bytes:
    return struct.pack(">H", (address * 7 + 3) & 0xFFFF)


def _request(tid: int, kind: str, gap_ms: int, index: int) -> bytes:
    """A request of ``kind``: a read whose register says what the upstream does
    (``kind``, the pause between its answer's bytes, a number of its own), or a
    write the guard refuses."""
    if kind == "refused":
        return mbap(tid, 1, struct.pack(">BHH", 6, 5, index))
    address = KINDS.index(kind) * 10000 + gap_ms * 1000 + index
    return mbap(tid, 1, struct.pack(">BHH", 3, address, 1))


def _expected(request: bytes) -> list[bytes]:
    """The answers a request may get: the upstream's (a read answered in time), the
    guard's refusal or the gateway's 0x0B / 0x0A (no answer in time; a renewed
    upstream connection not up yet)."""
    tid = (request[0] << 8) | request[1]
    if request[7] == 6:
        return [mbap(tid, 1, bytes.fromhex("86 01"))]
    address = (request[8] << 8) | request[9]
    own = [mbap(tid, 1, bytes([0x83, code])) for code in (0x0B, 0x0A)]
    if address // 10000 == SILENT:
        return own
    return [mbap(tid, 1, b"\x03\x02" + _value(address)), *own]


async def _answer(writer: asyncio.StreamWriter, req: bytes) -> None:
    """The upstream of the runs below, one request after the other as a Modbus server
    answers: a streamed answer a byte every 0..N ms, no answer, or an answer 1.5
    timeouts late (the register read says which)."""
    address = (req[8] << 8) | req[9]
    kind, gap = address // 10000, (address // 1000) % 10 / 1000
    if kind == SILENT:
        return
    answer = req[:2] + mbap(0, req[6], b"\x03\x02" + _value(address))[2:]
    if kind == LATE:
        await asyncio.sleep(1.5 * PROPERTY_TIMEOUT)
        writer.write(answer)
    elif gap == 0:
        writer.write(answer)
    else:
        await write_slowly(writer, answer, gap)


async def _client(
    port: int, script: list[tuple[str, int, int]], first_tid: int, depth: int
) -> dict[str, Any]:
    """Send the script's requests (``kind``, pause before it in ms: 0 pipelines it
    with the one before, the answer's byte gap in ms), at most ``depth`` in flight,
    and read what comes back until every request has an answer (or nothing more
    comes)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    requests = [
        _request(first_tid + i, kind, gap, i) for i, (kind, _pause, gap) in enumerate(script)
    ]
    got = bytearray()
    answers = [0]
    more = asyncio.Event()

    async def receive() -> None:
        while answers[0] < len(requests):
            part = await asyncio.wait_for(reader.read(4096), 10 * PROPERTY_TIMEOUT)
            if not part:
                return
            got.extend(part)
            count, pos = 0, 0
            while pos + 6 <= len(got):
                pos += 6 + ((got[pos + 4] << 8) | got[pos + 5])
                count += pos <= len(got)
            answers[0] = count
            more.set()

    receiving = asyncio.ensure_future(receive())
    for sent, (request, (_kind, pause, _gap)) in enumerate(zip(requests, script, strict=True)):
        while sent - answers[0] >= depth and not receiving.done():
            more.clear()
            waiter = asyncio.ensure_future(more.wait())
            await asyncio.wait([receiving, waiter], return_when=asyncio.FIRST_COMPLETED)
            waiter.cancel()
        if pause:
            await asyncio.sleep(pause / 1000)
        writer.write(request)
    try:
        await receiving
    except TimeoutError:
        pass
    sockname = writer.get_extra_info("sockname")
    writer.close()
    return {"requests": requests, "got": bytes(got), "peer": f"{sockname[0]}:{sockname[1]}"}


def _check(run: dict[str, Any]) -> list[str]:
    """What is wrong with what one client received: it must parse as whole MBAP
    ADUs, each an answer its request may get, one per request (none duplicated,
    none invented, none missing), the proxy's own answers after the answers to
    every earlier request."""
    requests: list[bytes] = run["requests"]
    got: bytes = run["got"]
    by_tid = {(r[0] << 8) | r[1]: i for i, r in enumerate(requests)}
    answered: dict[int, int] = {}  # request index -> position of its answer
    wrong = []
    pos = 0
    while pos < len(got):
        if len(got) - pos < 8 or got[pos + 2 : pos + 4] != b"\x00\x00":
            return [*wrong, f"not a whole MBAP ADU at byte {pos}: {got[pos:].hex(' ')}"]
        end = pos + 6 + ((got[pos + 4] << 8) | got[pos + 5])
        adu = got[pos:end]
        if end > len(got):
            return [*wrong, f"an answer cut short at byte {pos}: {adu.hex(' ')}"]
        index = by_tid.get((adu[0] << 8) | adu[1])
        if index is None or adu not in _expected(requests[index]):
            wrong.append(f"invented: {adu.hex(' ')}")
        elif index in answered:
            wrong.append(f"duplicated: {adu.hex(' ')}")
        else:
            answered[index] = len(answered)
            if adu[7] & 0x80:  # made by the proxy: after every earlier request's answer
                early = [
                    i for i in range(index) if answered.get(i, len(requests)) > answered[index]
                ]
                if early:
                    wrong.append(f"{adu.hex(' ')} before the answers to requests {early}")
        pos = end
    missing = [i for i in range(len(requests)) if i not in answered]
    if missing:
        wrong.append(f"no answer to requests {missing}")
    return wrong


@asynccontextmanager
async def engine_here(
    handle: Handler, shared: bool, items: list[Any], timeout: float = PROPERTY_TIMEOUT
) -> AsyncIterator[tuple[ProxyEngine, int]]:
    """The engine on this loop (``--timeout``, writes to R0..R100 refused) in front
    of an upstream served by ``handle``: the engine and its port; what it observes
    goes to ``items``."""
    made: list[Stream] = []

    def new_stream(transport: Transport, client: str, server: str) -> Stream:
        made.append(Stream(len(made), transport, client, server))
        return made[-1]

    server, upstream_port = await start_upstream(handle)
    config = ProxyConfig(
        upstream_host="127.0.0.1",
        upstream_port=upstream_port,
        listen_port=0,
        timeout=timeout,
        share_upstream=shared,
        guard=Guard.from_options(False, [], ["hr:0-100"]),
    )
    engine = ProxyEngine(config, Observer(items.append, new_stream))
    _, port = await engine.start()
    serving = asyncio.ensure_future(engine.serve())
    try:
        yield engine, port
    finally:
        engine.request_stop()
        await serving
        server.close()


async def _interleave(
    scripts: list[list[tuple[str, int, int]]], shared: bool, depth: int
) -> list[str]:
    """The engine between ``scripts``' clients and :func:`_answer`'s upstream; what
    is wrong, over every client (and its observed bytes: the client's two streams
    together hold exactly what it received)."""
    items: list[Chunk | Event] = []
    async with engine_here(answering(_answer), shared, items) as (_engine, port):
        runs = await asyncio.gather(
            *(_client(port, script, 1 + 1000 * i, depth) for i, script in enumerate(scripts))
        )
    wrong = []
    for run in runs:
        wrong += _check(run)
        observed = b"".join(
            item.data
            for item in items
            if isinstance(item, Chunk)
            and item.direction is Direction.S2C
            and item.stream.client == run["peer"]
        )
        if observed != run["got"]:
            wrong.append(f"observed {observed.hex(' ')}, received {run['got'].hex(' ')}")
    return wrong


_STEP = st.tuples(
    st.sampled_from(["streamed"] * 6 + ["refused"] * 3 + ["silent", "late"]),
    st.sampled_from([0, 0, 0, 1, 3, 8]),
    st.integers(0, 3),
)


@MODES
@settings(
    max_examples=8,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    scripts=st.lists(st.lists(_STEP, min_size=1, max_size=12), min_size=1, max_size=3),
    depth=st.integers(1, 4),
)
def test_any_interleaving_gives_each_request_one_whole_answer_in_its_place(
    shared: bool, scripts: list[list[tuple[str, int, int]]], depth: int
) -> None:
    """Random interleavings of streamed answers (random byte gaps), refusals,
    timeouts and late answers, pipelined or not, one to three clients: every byte
    stream a client receives is whole MBAP ADUs, each the answer to one of its
    requests, none duplicated, none invented, the proxy's own in their places."""
    assert asyncio.run(_interleave(scripts, shared, depth)) == []


@MODES
def test_many_requests_of_many_clients_each_get_one_whole_answer(shared: bool) -> None:
    """The same, as a stress run: 3 clients of 40 requests each, 2 in flight, random
    but fixed (about a fifth of them refused, a sixth answered 0x0B)."""
    rng = random.Random(f"whole-{shared}")
    kinds = ["streamed"] * 12 + ["refused"] * 5 + ["silent", "late"]
    scripts = [
        [(rng.choice(kinds), rng.choice([0, 0, 0, 1, 3]), rng.randrange(3)) for _ in range(40)]
        for _ in range(3)
    ]
    assert asyncio.run(_interleave(scripts, shared, 2)) == []


def test_answers_waiting_their_turn_stop_the_reading_not_the_memory() -> None:
    """A read whose answer the upstream sends in two parts 1.6 s apart (longer than
    the 1 s timeout: it is half-way then, so it gets one more), and once its first
    part is here 15,000 writes the guard refuses, pipelined: the refusals wait for the read's
    answer, and once more than :data:`HOLD_LIMIT` bytes of them wait the client's
    requests are no longer read until they are written. The proxy's own pause is
    not the client stalling half-way through a request (it is not dropped as a
    slowloris). All 15,001 answers come, whole and in order."""
    writes = 15_000
    read = mbap(1, 1, struct.pack(">BHH", 3, 300, 1))
    answer = mbap(1, 1, b"\x03\x02" + _value(300))

    async def late(writer: asyncio.StreamWriter, req: bytes) -> None:
        if req == read:
            writer.write(answer[:3])
            await asyncio.sleep(1.6)
        writer.write(req[:2] + answer[2:] if req != read else answer[3:])

    items: list[Any] = []

    async def main() -> tuple[bytes, int]:
        async with engine_here(answering(late), False, items, 1.0) as (engine, port):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(mbap(0, 1, read[7:]))  # the upstream connection is up
            assert await asyncio.wait_for(reader.readexactly(len(answer)), 5)
            most = 0

            async def watch() -> None:
                nonlocal most
                while True:
                    for client in engine.clients:
                        most = max(most, client.held_bytes)
                    await asyncio.sleep(0.002)

            watching = asyncio.ensure_future(watch())
            writer.write(read)
            got = await asyncio.wait_for(reader.readexactly(3), 5)  # the answer is coming
            for i in range(writes):
                writer.write(mbap(2 + i, 1, struct.pack(">BHH", 6, 5, i & 0xFF)))
            want = len(answer) + writes * 9
            while len(got) < want:
                try:
                    part = await asyncio.wait_for(reader.read(want), 30)
                except ConnectionResetError:
                    break  # dropped: the notices say why
                if not part:
                    break
                got += part
            watching.cancel()
            writer.close()
        return got, most

    got, most = asyncio.run(main())
    refusals = b"".join(mbap(2 + i, 1, b"\x86\x01") for i in range(writes))
    notices = [i.info["message"] for i in items if isinstance(i, Event) and "message" in i.info]
    assert got == answer + refusals, [n for n in notices if "refused" not in n]
    # the refusals of one read of the client's (at most 64 KiB of requests) may
    # come on top of the limit before the reading stops
    assert HOLD_LIMIT < most < HOLD_LIMIT + (64 * 1024 // 12 + 1) * 9, most
