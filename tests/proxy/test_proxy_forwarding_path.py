"""The forwarding process's per-request path: one request at a time, the common case
(a whole clean ADU per read, the guard off, a client's own upstream connection),
runs inline (``Client.buffer_updated``, ``LinkBase.data_received``); what it counts
and keeps must be what the general path counts and keeps.

Real parts: the engine on its own thread (:class:`~mbmon.proxy.runner.ProxyThread`),
a raw asyncio upstream on 127.0.0.1, a raw-socket client.
"""

from __future__ import annotations

import socket
import struct
import threading
from collections.abc import Callable
from concurrent.futures import Future
from typing import TypeVar

from mbmon.hub import Hub
from mbmon.pipeline import Pipeline
from mbmon.proxy.config import ProxyConfig
from mbmon.proxy.engine import ProxyEngine
from mbmon.proxy.observer import Observer
from mbmon.proxy.runner import ProxyThread
from tests.proxy.test_proxy_reads import _expected, upstream

T = TypeVar("T")


def in_loop(engine: ProxyEngine, fn: Callable[[], T]) -> T:
    """``fn()`` run in the engine's loop thread, between its callbacks."""
    done: Future[T] = Future()
    engine.loop.call_soon_threadsafe(lambda: done.set_result(fn()))
    return done.result(10)


def _one_by_one(port: int, unit: int, n: int) -> bytes:
    """``n`` requests, each sent once the answer to the one before is in."""
    got = bytearray()
    with socket.create_connection(("127.0.0.1", port), timeout=20) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for tid in range(n):
            sock.sendall(struct.pack(">HHHBBHH", tid, 0, 6, unit, 3, tid % 7, 1 + tid % 5))
            want = len(_expected(unit, tid + 1))
            while len(got) < want:
                part = sock.recv(4096)
                assert part, "the proxy closed the connection"
                got += part
    return bytes(got)


def test_answered_requests_leave_the_deadline_queue_at_once() -> None:
    # a request lives as long as its round trip: with the default 3-s timeout, 1,500
    # answered requests used to wait in the timeout queue (and keep their bytes) until
    # the next expiry, 3 s later
    n = 1500
    with upstream() as up:
        hub = Hub(Pipeline())
        config = ProxyConfig(upstream_host="127.0.0.1", upstream_port=up, listen_port=0)
        assert config.timeout >= 3.0
        engine = ProxyEngine(config, Observer(hub.put, hub.new_stream), submit=hub.submit)
        thread = ProxyThread(engine, on_exit=hub.stop)
        _, port = thread.start()
        runner = threading.Thread(target=hub.run, daemon=True)
        runner.start()
        try:
            assert _one_by_one(port, 9, n) == _expected(9, n)
            waiting = in_loop(engine, lambda: list(engine._deadlines))
            stats = in_loop(engine, engine.stats.as_dict)
        finally:
            thread.stop()
            assert thread.join(10)
            runner.join(10)
    assert len(waiting) <= 1, f"{len(waiting)} requests still in the timeout queue"
    assert all(entry.done for entry in waiting)
    assert (stats["requests"], stats["responses"]) == (n, n)
    assert stats["bytes_from_clients"] == 12 * n
    assert stats["bytes_to_clients"] == len(_expected(9, n))


def test_the_pipe_takes_the_observations_in_few_batches() -> None:
    """A request every millisecond for 0.2 s: the forwarding process writes its copies
    to the observation pipe in batches of ``handover`` (10 ms), about 20 writes, not
    one every 2 ms (about 100): each batch wakes the observing process's reader and
    hub threads, whose per-batch work was over a microsecond a request at 8 clients
    (docs/performance.md). Every copy still arrives, in order."""
    import asyncio
    import os

    from mbmon.model import Direction, Stream, Transport
    from mbmon.proxy.remote import CHUNK_HEAD, PipeObserver, PipeOut

    config = ProxyConfig(upstream_host="127.0.0.1", upstream_port=1, listen_port=0)
    stream = Stream(0, Transport.TCP, "127.0.0.1:5000", "127.0.0.1:502")
    sent = [struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, 0, 10) for tid in range(200)]
    commits = 0
    elapsed = 0.0
    read_fd, write_fd = os.pipe()

    async def run() -> None:
        nonlocal commits, elapsed
        loop = asyncio.get_running_loop()
        out = PipeOut(write_fd, loop, lambda: None)
        commit = out.commit

        def counted() -> None:
            nonlocal commits
            commits += 1
            commit()

        out.commit = counted  # type: ignore[method-assign]
        obs = PipeObserver(out, lambda *a: stream, max_backlog=10**6)
        obs.bind(lambda fn: loop.call_later(config.handover, fn))
        start = loop.time()
        for raw in sent:
            obs.chunk(stream, Direction.C2S, raw, 1.0)
            await asyncio.sleep(0.001)
        elapsed = loop.time() - start
        await asyncio.sleep(2 * config.handover)
        out.finish()

    asyncio.run(run())
    data = bytearray()
    while part := os.read(read_fd, 1 << 16):
        data += part
    os.close(read_fd)
    got, pos = [], 0
    while pos < len(data):
        *_, length = CHUNK_HEAD.unpack_from(data, pos)
        got.append(bytes(data[pos + CHUNK_HEAD.size : pos + CHUNK_HEAD.size + length]))
        pos += CHUNK_HEAD.size + length
    assert got == sent
    # a loaded machine stretches the run: the bound is per 10 ms of it
    assert commits <= elapsed / 0.01 + 3, f"{commits} writes in {elapsed:.3f} s"
