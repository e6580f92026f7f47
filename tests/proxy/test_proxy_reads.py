"""The engine's socket reads: every connection reads into the engine's one buffer
(:data:`mbmon.proxy.reader.READ_BUFFER`), so bursts larger than it, and several
clients whose reads alternate on it, must come through whole, in order, unmixed —
forwarded and observed byte for byte.

Real parts: a raw asyncio Modbus/TCP upstream on 127.0.0.1 (its own thread), the
engine on its own thread, the hub running in another, raw-socket clients.
"""

from __future__ import annotations

import asyncio
import socket
import struct
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from mbmon.hub import Hub
from mbmon.model import Chunk, Direction
from mbmon.pipeline import Pipeline
from mbmon.proxy.config import ProxyConfig
from mbmon.proxy.engine import ProxyEngine
from mbmon.proxy.observer import Observer
from mbmon.proxy.reader import READ_BUFFER
from mbmon.proxy.runner import ProxyThread


class _Upstream(asyncio.Protocol):
    """Answers FC 03 with ``count`` registers holding the unit id and the tid's low byte."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport: Any = transport
        self.buf = b""

    def data_received(self, data: bytes) -> None:
        buf = self.buf + data
        out = []
        while len(buf) >= 7:
            n = 6 + ((buf[4] << 8) | buf[5])
            if len(buf) < n:
                break
            tid, unit, count = buf[0:2], buf[6], (buf[10] << 8) | buf[11]
            body = bytes([3, 2 * count]) + bytes([unit, tid[1]]) * count
            out.append(tid + struct.pack(">HH", 0, len(body) + 1) + bytes([unit]) + body)
            buf = buf[n:]
        self.buf = buf
        if out:
            self.transport.write(b"".join(out))


@contextmanager
def upstream() -> Iterator[int]:
    loop = asyncio.new_event_loop()
    server = loop.run_until_complete(loop.create_server(_Upstream, "127.0.0.1", 0))
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        server.close()
        loop.run_until_complete(server.wait_closed())
        loop.close()


class _Chunks:
    """A hub listener keeping every chunk, per stream and direction."""

    def __init__(self) -> None:
        self.data: dict[tuple[str, Direction], bytearray] = {}

    def on_chunk(self, chunk: Chunk) -> None:
        key = (chunk.stream.client, chunk.direction)
        self.data.setdefault(key, bytearray()).extend(chunk.data)


@contextmanager
def running_proxy(up: int) -> Iterator[tuple[int, _Chunks]]:
    hub = Hub(Pipeline())
    chunks = _Chunks()
    hub.add_listener(chunks)
    config = ProxyConfig(upstream_host="127.0.0.1", upstream_port=up, listen_port=0)
    engine = ProxyEngine(config, Observer(hub.put, hub.new_stream), submit=hub.submit)
    thread = ProxyThread(engine, on_exit=hub.stop)
    _, port = thread.start()
    runner = threading.Thread(target=hub.run, daemon=True)
    runner.start()
    try:
        yield port, chunks
    finally:
        thread.stop()
        assert thread.join(10)
        runner.join(10)
        assert not runner.is_alive()


def _requests(unit: int, n: int) -> bytes:
    return b"".join(
        struct.pack(">HHHBBHH", tid, 0, 6, unit, 3, tid % 7, 1 + tid % 5) for tid in range(n)
    )


def _expected(unit: int, n: int) -> bytes:
    out = []
    for tid in range(n):
        count = 1 + tid % 5
        body = bytes([3, 2 * count]) + bytes([unit, tid & 0xFF]) * count
        out.append(struct.pack(">HHHB", tid, 0, len(body) + 1, unit) + body)
    return b"".join(out)


def _burst(port: int, unit: int, n: int, results: dict[int, bytes]) -> None:
    """Send ``n`` pipelined requests in one write and read every answer back."""
    want = len(_expected(unit, n))
    with socket.create_connection(("127.0.0.1", port), timeout=20) as sock:
        sender = threading.Thread(target=sock.sendall, args=(_requests(unit, n),))
        sender.start()
        got = bytearray()
        while len(got) < want:
            part = sock.recv(65536)
            if not part:
                break
            got += part
        sender.join(20)
        results[unit] = bytes(got)
        results[-unit] = sock.getsockname()[1].to_bytes(2, "big")


def test_a_burst_larger_than_the_read_buffer_is_forwarded_and_observed_whole() -> None:
    n = 8000  # 96,000 bytes of requests in one write: more than one read takes
    assert 12 * n > READ_BUFFER
    results: dict[int, bytes] = {}
    with upstream() as up, running_proxy(up) as (port, chunks):
        _burst(port, 1, n, results)
    assert results[1] == _expected(1, n)
    client = f"127.0.0.1:{int.from_bytes(results[-1], 'big')}"
    assert bytes(chunks.data[(client, Direction.C2S)]) == _requests(1, n)
    assert bytes(chunks.data[(client, Direction.S2C)]) == _expected(1, n)


def test_clients_reading_in_turn_into_the_one_buffer_never_mix() -> None:
    n = 3000  # each client 36,000 bytes in one write, six at once
    results: dict[int, bytes] = {}
    with upstream() as up, running_proxy(up) as (port, chunks):
        threads = [
            threading.Thread(target=_burst, args=(port, unit, n, results)) for unit in range(1, 7)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
    for unit in range(1, 7):
        assert results[unit] == _expected(unit, n), f"client {unit} got other bytes"
        client = f"127.0.0.1:{int.from_bytes(results[-unit], 'big')}"
        assert bytes(chunks.data[(client, Direction.C2S)]) == _requests(unit, n)
        assert bytes(chunks.data[(client, Direction.S2C)]) == _expected(unit, n)
