"""The proxy engine: an asyncio Modbus/TCP forwarder that answers like a gateway.

Forward first, observe second (DESIGN rule 9). Each client connection is an
:class:`asyncio.Protocol`; its bytes are framed by the sans-I/O
:class:`~mbmon.protocol.mbap.MbapDecoder` (so the proxy knows where each request
ends, its transaction id, unit and what it writes), checked by the
:class:`~mbmon.proxy.guard.Guard` and written to the upstream as soon as a read
completes them. Upstream answers are framed the same way, matched to their
request by transaction id and written to their client at once. Only then does a
copy go to the observer (:class:`Observer`, which hands chunks and events to
the hub's thread-safe queue): nothing the hub, the pipeline or a listener does
can delay or change the traffic.

What the hub sees, per client connection, is one stream
``client endpoint -> upstream endpoint`` carrying the bytes the client sent to
the upstream (C2S) and the upstream's answers it received (S2C), and one stream
``client endpoint -> the proxy's listening endpoint`` with what the proxy answered
itself (0x0A, 0x0B, guard refusals, and the refused requests): together exactly
what the client sent and received. The client's CONNECT names the second
(``answers_on``) so the pipeline pairs its answers with the first's requests,
marked ``made by the proxy``. Events: CONNECT/DISCONNECT (``how`` fin/rst, ``by``
client/proxy, ``reason``), NOTICE (upstream lost and back, answers dropped,
clients dropped) and GUARD (refused writes and clients).

Gateway rules:

* upstream refused or unreachable: every request is answered with exception
  0x0A (gateway path unavailable); the upstream is tried again on the next
  request after a backoff (``backoff_min`` doubling up to ``backoff_max``);
* no answer within ``timeout``: exception 0x0B (gateway target device failed to
  respond); an answer that comes later is dropped and logged, never delivered;
  an upstream connection that holds half an answer at that moment is reset;
* upstream closed or reset with requests in flight: those are answered 0x0B;
* an answer the proxy makes (0x0A, 0x0B, a guard refusal) is never written into
  the middle of an answer being forwarded, and keeps its request's place
  (:meth:`~mbmon.proxy.client.Client.send_own`);
* the client connection stays open through all of this.

Clients: a client whose bytes are not Modbus/TCP (protocol id != 0, a length
outside 2..254) is dropped, that client only; a client whose request stays
incomplete for ``timeout`` (slowloris) or that does not read its responses
for ``timeout`` (its send buffer full) is dropped; a client that half-closes
gets the answers to its requests in flight first.

Modes: one upstream connection per client, transaction ids untouched
(default, byte-transparent), or ``share_upstream``: every client over one
upstream connection with transaction ids remapped (responses get the client's
own id back).

Threads: the engine runs on one asyncio loop (:class:`~mbmon.proxy.runner.ProxyThread`
gives it its own thread; :class:`~mbmon.proxy.remote.ProxyProcess` its own process, as the
TCP proxy runs it); the observer's ``put`` is the hub's thread-safe queue (or,
from a child process, a pipe), consumed by ``hub.run`` in another thread. If
the hub falls behind by more than ``max_backlog`` items, chunks are forwarded
but not observed (counted, and reported by a NOTICE when observation resumes),
so memory stays bounded.

Modules: :mod:`~mbmon.proxy.config` (settings, counters), :mod:`~mbmon.proxy.observer`
(the way to the hub), :mod:`~mbmon.proxy.client` (the client side),
:mod:`~mbmon.proxy.link` and :mod:`~mbmon.proxy.upstream` (the upstream side),
this module (the listening socket, the shared timeout queue, the gateway's own
answers), :mod:`~mbmon.proxy.runner` (the thread, and the choice of thread or
process) and :mod:`~mbmon.proxy.keepalive`.
"""

from __future__ import annotations

import asyncio
import socket
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from mbmon.model import Chunk, Event, EventKind
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_exception
from mbmon.proxy.client import Client
from mbmon.proxy.config import GATEWAY_PATH_UNAVAILABLE, ProxyConfig, ProxyStats, endpoint
from mbmon.proxy.link import Link, Pending
from mbmon.proxy.observer import Observer
from mbmon.proxy.reader import READ_BUFFER
from mbmon.proxy.upstream import TcpLink

__all__ = ["ProxyEngine"]


class ProxyEngine:
    """The listening socket, the clients and the upstream links of one proxy run."""

    def __init__(
        self,
        config: ProxyConfig,
        observer: Observer,
        submit: Callable[[Callable[[], list[Chunk | Event]]], None] | None = None,
        *,
        upstream: Callable[[ProxyEngine], Any] | None = None,
        front: Callable[[ProxyEngine], Any] | None = None,
    ) -> None:
        """``submit`` (``hub.submit``): hand observations over in batches, once per
        loop iteration (:meth:`Observer.bind`); without it, item by item.

        ``upstream(engine)`` makes the one link every client shares instead of a TCP
        upstream (an RTU bus: :mod:`mbmon.proxy.serial`); ``front(engine)`` makes the
        one client instead of a listening socket (an RTU master's serial port). Both
        run in the loop's thread at :meth:`start`, and may raise ``OSError``.
        """
        self.config = config
        self.observer = observer
        self._submit = submit
        self._upstream_factory = upstream
        self._front_factory = front
        self.front: Any = None
        self.stats = ProxyStats()
        self.clients: set[Client] = set()
        self.shared: Link | None = None  # the shared TcpLink, or the upstream factory's link
        self.loop: asyncio.AbstractEventLoop = None  # type: ignore[assignment]
        self.address: tuple[str, int] | None = None
        #: the proxy as an endpoint (its listening address): the server side of the
        #: streams of its own answers (:meth:`Client.send_own`)
        self.name = "proxy"
        self._server: asyncio.base_events.Server | None = None
        self._stop: asyncio.Event | None = None
        #: requests waiting for their answer, in deadline order (one timeout for all)
        self._deadlines: deque[Pending] = deque()
        self._expiry: asyncio.TimerHandle | None = None
        #: the upstream as last seen (for the live monitor): up, unavailable (why), ...
        self.upstream_state = "not connected yet"
        #: every socket of the loop reads into this, one read at a time
        #: (:class:`~mbmon.proxy.reader.Reader`)
        self.read_buffer = memoryview(bytearray(READ_BUFFER))

    def figures(self) -> dict[str, Any]:
        """The proxy's own figures for the live monitor's header (read from any thread)."""
        stats = self.stats
        figures: dict[str, Any] = {
            "clients": len(self.clients),
            "upstream": self.upstream_state,
            "guard refusals": stats.guard_refusals,
            "0x0A answers": stats.exceptions_0a,
            "0x0B answers": stats.exceptions_0b,
        }
        if self.front is not None:  # an RTU master gets silence instead of 0x0A/0x0B
            figures["left silent"] = stats.unanswered
        return figures

    def arm(self, entry: Pending) -> None:
        """Start ``entry``'s timeout: one loop timer serves every request, since all
        share one timeout and so expire in the order they were sent. The requests
        answered already at the queue's head leave it now, not at the next expiry: a
        request lives as long as its round trip, not ``timeout`` (at 20,000 requests
        a second, 3 s of them kept alive made the collector's full passes walk them
        again and again, and held megabytes)."""
        loop = self.loop
        entry.deadline = deadline = loop.time() + self.config.timeout
        dq = self._deadlines
        while dq and dq[0].done:
            dq.popleft()
        dq.append(entry)
        if self._expiry is None:
            self._expiry = loop.call_at(deadline, self._expire_due)

    def _expire_due(self) -> None:
        """Expire every request past its deadline; re-arm for the next one."""
        self._expiry = None
        dq = self._deadlines
        now = self.loop.time()
        while dq:
            entry = dq[0]
            if entry.done:
                dq.popleft()
                continue
            if entry.deadline is not None and entry.deadline > now:
                break
            dq.popleft()
            link = entry.link
            if isinstance(link, TcpLink):  # only a TCP link's requests are armed here
                link.expire(entry)
            else:
                entry.done = True
        while dq and dq[0].done:
            dq.popleft()
        if dq and dq[0].deadline is not None:
            self._expiry = self.loop.call_at(dq[0].deadline, self._expire_due)

    def answer_exception(self, entry: Pending, code: int) -> None:
        """Answer ``entry``'s client with exception ``code`` (0x0A or 0x0B)."""
        client = entry.client
        client.outstanding.discard(entry)
        if client.closed:
            return
        if client.silent:
            client.unanswered(entry, code)
            return
        if code == GATEWAY_PATH_UNAVAILABLE:
            self.stats.exceptions_0a += 1
        else:
            self.stats.exceptions_0b += 1
        client.send_own(
            encode_adu(entry.tid, entry.unit, encode_exception(entry.fc, code)),
            time.time(),
            entry.seq,
        )

    async def start(self) -> tuple[str, int]:
        """Bind the listening socket; the address actually bound (port 0 picks one)."""
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        loop = self.loop
        delay = self.config.handover
        if delay > 0:
            self.observer.bind(lambda fn: loop.call_later(delay, fn), self._submit)
        else:
            self.observer.bind(loop.call_soon, self._submit)
        self.loop.set_exception_handler(self._loop_error)
        cfg = self.config
        if self._upstream_factory is not None:
            self.shared = self._upstream_factory(self)
            upstream_text = f"{cfg.upstream} (RTU bus)"
        else:
            upstream_text = cfg.upstream + (" (shared connection)" if cfg.share_upstream else "")
            if cfg.share_upstream:
                self.shared = TcpLink(self, None)
        if self._front_factory is not None:
            try:
                self.front = self._front_factory(self)
            except BaseException:
                if self.shared is not None:
                    self.shared.close()
                raise
            self.address = (str(self.front.name), 0)
            where = str(self.front.name)
        else:
            self._server = await self.loop.create_server(
                lambda: Client(self),
                cfg.listen_host,
                cfg.listen_port,
                reuse_address=True,
                family=socket.AF_INET6 if ":" in cfg.listen_host else socket.AF_INET,
            )
            sock = self._server.sockets[0]
            name = sock.getsockname()
            self.address = (str(name[0]), int(name[1]))
            where = self.name = endpoint(*self.address)
        self.observer.event(
            None,
            EventKind.NOTICE,
            {
                "message": f"proxy listening on {where}, "
                f"upstream {upstream_text}, guard {cfg.guard.describe()}",
            },
        )
        if self.shared is not None:
            self.shared.connect()
        self.loop.create_task(self._sweep())
        return self.address

    def _loop_error(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """An error inside a callback (a bug, never a peer's bytes): one notice, the
        loop goes on, no traceback on the console."""
        exc = context.get("exception")
        what = context.get("message", "error")
        if exc is not None:
            what = f"{what}: {type(exc).__name__}: {exc}"
        self.observer.event(None, EventKind.NOTICE, {"message": f"proxy internal error: {what}"})

    async def serve(self) -> None:
        """Run until :meth:`request_stop`; then close every connection."""
        assert self._stop is not None
        await self._stop.wait()
        await self._shutdown()

    def request_stop(self) -> None:
        """End :meth:`serve` (call in the loop's thread)."""
        if self._stop is not None:
            self._stop.set()

    async def _shutdown(self) -> None:
        if self._server is not None:
            self._server.close()
        for client in list(self.clients):
            client.drop("the proxy is stopping", count=False)
        if self.shared is not None:
            self.shared.close()
        await asyncio.sleep(0)  # let the transports call connection_lost
        if self._server is not None:
            try:
                await asyncio.wait_for(self._server.wait_closed(), 1.0)
            except TimeoutError:
                pass

    async def _sweep(self) -> None:
        """Drop clients stuck half-way through a request or not reading their answers."""
        timeout = self.config.timeout
        period = min(0.25, timeout / 4)
        loop = self.loop
        while True:
            await asyncio.sleep(period)
            now = loop.time()
            for client in list(self.clients):
                if client.closed:
                    continue
                since = client.partial_since
                # while the proxy does not read the client (answers waiting their turn,
                # or its own unread), it is not half-way through a request by its doing
                reading = not client.hold_paused and client.paused_since is None
                if since is not None and reading and now - since > timeout:
                    client.drop(
                        f"request incomplete for more than {timeout:g} s "
                        f"({client.received - client.consumed} bytes waiting)"
                    )
                    continue
                since = client.paused_since
                if since is not None and now - since > timeout:
                    waiting = client.transport.get_write_buffer_size() if client.transport else 0
                    client.drop(
                        f"client has not read its responses for {timeout:g} s "
                        f"({waiting} bytes waiting)"
                    )
