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
