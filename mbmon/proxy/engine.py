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
``client endpoint -> upstream endpoint`` carrying exactly the bytes the client
sent (C2S) and exactly the bytes the client received (S2C), including the
exception responses the proxy made itself, plus events: CONNECT/DISCONNECT
(``how`` fin/rst, ``by`` client/proxy, ``reason``), NOTICE (upstream lost and
back, answers dropped, clients dropped) and GUARD (refused writes and clients).

Gateway rules:

* upstream refused or unreachable: every request is answered with exception
  0x0A (gateway path unavailable); the upstream is tried again on the next
  request after a backoff (``backoff_min`` doubling up to ``backoff_max``);
* no answer within ``timeout``: exception 0x0B (gateway target device failed to
  respond); an answer that comes later is dropped and logged, never delivered;
  an upstream connection that holds half an answer at that moment is reset;
* upstream closed or reset with requests in flight: those are answered 0x0B;
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

Threads: the engine runs on one asyncio loop (:class:`ProxyThread` gives it its
own thread; :class:`~mbmon.proxy.remote.ProxyProcess` its own process, as the
TCP proxy runs it); the observer's ``put`` is the hub's thread-safe queue (or,
from a child process, a pipe), consumed by ``hub.run`` in another thread. If
the hub falls behind by more than ``max_backlog`` items, chunks are forwarded
but not observed (counted, and reported by a NOTICE when observation resumes),
so memory stays bounded.
"""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, Protocol

from mbmon.model import (
    Chunk,
    Direction,
    Event,
    EventKind,
    Stream,
    Transport,
    fast_constructor,
)
from mbmon.protocol.mbap import MbapDecoder, encode_adu
from mbmon.protocol.pdu import encode_exception
from mbmon.proxy.guard import ClientFilter, Guard

__all__ = [
    "GATEWAY_PATH_UNAVAILABLE",
    "GATEWAY_TARGET_FAILED",
    "Observer",
    "ProxyConfig",
    "ProxyEngine",
    "ProxyStats",
    "ProxyThread",
    "endpoint",
    "keepalive",
]

GATEWAY_PATH_UNAVAILABLE = 0x0A
GATEWAY_TARGET_FAILED = 0x0B

#: How far (chunks and events) the hub may fall behind before chunks are forwarded
#: without a copy: bounds the queue's memory (about 250 bytes an item).
MAX_BACKLOG = 50_000

#: Seconds observations wait to go to the hub together (:attr:`ProxyConfig.handover`).
HANDOVER = 0.002

#: How many answered-with-0x0B (or orphaned) upstream transaction ids are remembered,
#: so that their late answers are recognised and dropped.
LATE_MEMORY = 4096

#: A client's upstream connection renewed after a gateway timeout stays open this many
#: ``timeout``\ s (while it owes answers, longer), so that the late answer is seen and
#: logged as dropped; at most ``MAX_RETIRED`` such connections per client (the oldest
#: closes first).
LINGER = 4
MAX_RETIRED = 2

#: How many bytes one read of a socket takes at most. The engine reads into one
#: buffer of its own (:class:`_Reader`): asyncio's plain protocols get a new
#: 256 KiB ``bytes`` per read, which glibc serves above its mmap threshold, so
#: every 12-byte request cost an mmap, page faults, an mremap and a munmap (a TLB
#: shootdown across the process's threads): half the engine's CPU per request
#: (docs/performance.md). A Modbus/TCP ADU is at most 260 bytes.
READ_BUFFER = 64 * 1024

#: The kernel send buffer of a client socket (the kernel doubles it): Modbus answers
#: are at most 260 bytes, so this holds hundreds; a client that leaves more unread
#: than this and the loop's 64 KiB is not reading, and is dropped after ``timeout``.
CLIENT_SNDBUF = 64 * 1024

#: TCP keepalive on every client and upstream socket: probes after this many idle
#: seconds, every ``KEEPALIVE_INTERVAL`` s, ``KEEPALIVE_COUNT`` unanswered ones close
#: the connection. A peer whose host vanished (power cut, cable pulled) without a
#: FIN or RST is noticed within about a minute instead of never (an idle client)
#: or at the next request's timeout (an idle upstream).
KEEPALIVE_IDLE = 30
KEEPALIVE_INTERVAL = 10
KEEPALIVE_COUNT = 3

_C2S = Direction.C2S
_S2C = Direction.S2C
_new_chunk = fast_constructor(Chunk)  # two per request: about twice as fast as Chunk(...)


def endpoint(host: str, port: int) -> str:
    """``HOST:PORT``, IPv6 as ``[ADDR]:PORT`` (the model's endpoint text)."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


@dataclass
class ProxyConfig:
    """Where to listen, where to forward, and the rules (see the module text)."""

    upstream_host: str
    upstream_port: int
    listen_host: str = "127.0.0.1"
    listen_port: int = 1502
    timeout: float = 3.0
    share_upstream: bool = False
    guard: Guard = field(default_factory=Guard)
    clients: ClientFilter = field(default_factory=ClientFilter)
    backoff_min: float = 0.05
    backoff_max: float = 1.0
    max_backlog: int = MAX_BACKLOG
    #: how long observations wait to be handed to the hub in one batch (0: once per
    #: loop iteration). 2 ms: the hub's thread wakes (and takes the GIL from the
    #: forwarding) a few hundred times a second instead of twice per request, which
    #: at one client cuts the hub's CPU per request by half or more (docs/performance.md)
    handover: float = HANDOVER
    #: the upstream's name when it is not a TCP server (an RTU bus: its serial port)
    upstream_name: str | None = None

    @property
    def upstream(self) -> str:
        if self.upstream_name is not None:
            return self.upstream_name
        return endpoint(self.upstream_host, self.upstream_port)


@dataclass
class ProxyStats:
    """Counters of a run, for the summary on exit (written by the engine's thread)."""

    clients: int = 0
    clients_refused: int = 0
    clients_dropped: int = 0
    requests: int = 0
    responses: int = 0
    exceptions_0a: int = 0
    exceptions_0b: int = 0
    guard_refusals: int = 0
    late_dropped: int = 0
    unanswered: int = 0  # RTU master requests left silent (gateway 0x0A/0x0B)
    unmatched_dropped: int = 0
    unmatched_forwarded: int = 0  # per client: answers with an unknown tid, forwarded
    upstream_renewed: int = 0  # per client: connections renewed after a gateway timeout
    upstream_connects: int = 0
    upstream_failures: int = 0
    bytes_from_clients: int = 0
    bytes_to_clients: int = 0
    not_observed: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def summary(self) -> str:
        """The one-paragraph summary printed on exit."""
        made = self.exceptions_0a + self.exceptions_0b + self.guard_refusals
        lines = [
            f"clients {self.clients} (refused {self.clients_refused}, "
            f"dropped {self.clients_dropped})",
            f"requests {self.requests}, responses {self.responses}",
            f"exceptions made by the proxy {made} (0x0A {self.exceptions_0a}, "
            f"0x0B {self.exceptions_0b}, guard {self.guard_refusals})",
            f"guard refusals {self.guard_refusals}, late answers dropped {self.late_dropped}, "
            f"unmatched answers dropped {self.unmatched_dropped}, "
            f"forwarded with an unknown tid {self.unmatched_forwarded}",
            f"upstream connections {self.upstream_connects} "
            f"(failed attempts {self.upstream_failures}, "
            f"renewed after a gateway timeout {self.upstream_renewed})",
            f"bytes client->server {self.bytes_from_clients}, "
            f"server->client {self.bytes_to_clients}",
        ]
        if self.unanswered:
            lines.append(
                f"RTU master requests left unanswered (silence for 0x0A/0x0B) {self.unanswered}"
            )
        if self.not_observed:
            lines.append(f"chunks forwarded but not observed (monitor behind) {self.not_observed}")
        return "\n".join(lines)


class Meter(Protocol):
    """What the observer reads to know its backlog: items taken so far."""

    seen: int


class Observer:
    """The engine's way to the hub: ``put`` (thread-safe), ``new_stream``, the clock.

    Chunks are skipped (and counted) while the hub is more than ``max_backlog``
    items behind; events always go through (they are few). ``meter`` tells how
    far behind: anything whose ``seen`` counts the items taken so far (the hub
    itself, :attr:`mbmon.hub.Hub.seen`; in the forwarding process, the pipe).

    Once :meth:`bind` gives it a scheduler (the loop's ``call_soon``, or a
    ``call_later`` of :attr:`ProxyConfig.handover`) and a ``submit``
    (``hub.submit``), items wait in a batch that is handed over after the
    forwarding that made them: one queue operation and one wake-up of the hub's
    thread per batch instead of per chunk.
    """

    def __init__(
        self,
        put: Callable[[Chunk | Event], None],
        new_stream: Callable[[Transport, str, str], Stream],
        *,
        meter: Meter | None = None,
        max_backlog: int = MAX_BACKLOG,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self._put = put
        self.new_stream = new_stream
        self.clock = clock
        self._meter = meter
        self._max_backlog = max_backlog
        self.sent = 0
        self.skipped = 0
        self._skipping = 0
        self._batch: list[Chunk | Event] = []
        self._call_soon: Callable[[Callable[[], None]], Any] | None = None
        self._submit: Callable[[Callable[[], list[Chunk | Event]]], None] | None = None

    def bind(
        self,
        call_soon: Callable[[Callable[[], None]], Any],
        submit: Callable[[Callable[[], list[Chunk | Event]]], None] | None = None,
    ) -> None:
        """Batch items until ``call_soon(flush)`` runs (``loop.call_soon``: this loop
        iteration; a ``call_later``: after a delay) and hand them over with ``submit``
        (in the loop's thread only); without ``submit``, items go one by one to
        ``put`` (an observer that hands batches over itself needs only the timer)."""
        self._call_soon = call_soon
        self._submit = submit

    def flush(self) -> None:
        """Hand the waiting batch over now."""
        batch = self._batch
        if batch and self._submit is not None:
            self._batch = []
            self._submit(lambda: batch)

    def _emit(self, item: Chunk | Event) -> None:
        call_soon = self._call_soon
        if call_soon is None or self._submit is None:
            self._put(item)
            return
        batch = self._batch
        batch.append(item)
        if len(batch) == 1:
            call_soon(self.flush)

    def chunk(self, stream: Stream, direction: Direction, data: bytes, ts: float) -> None:
        if self._admit(ts):
            self._emit(_new_chunk(ts, stream, direction, data))

    def _admit(self, ts: float) -> bool:
        """Whether a chunk at ``ts`` is observed (counted as sent): not while the hub
        is more than ``max_backlog`` behind (skipped, counted); the first one after a
        skip comes after a NOTICE that says how many were not observed."""
        meter = self._meter
        if meter is not None and self.sent - meter.seen > self._max_backlog:
            self.skipped += 1
            self._skipping += 1
            return False
        if self._skipping:
            n, self._skipping = self._skipping, 0
            self.event(
                None,
                EventKind.NOTICE,
                {"message": f"{n} chunks were forwarded but not observed: the monitor fell behind"},
                ts,
            )
        self.sent += 1
        return True

    def event(
        self, stream: Stream | None, kind: EventKind, info: dict[str, Any], ts: float | None = None
    ) -> None:
        self.sent += 1
        self._emit(Event(self.clock() if ts is None else ts, stream, kind, info))


class _Pending:
    """One request in flight upstream."""

    __slots__ = (
        "client",
        "deadline",
        "done",
        "extended",
        "fc",
        "link",
        "raw",
        "tid",
        "unit",
        "utid",
    )

    def __init__(self, client: _Client, tid: int, utid: int, unit: int, fc: int, raw: bytes):
        self.client = client
        self.tid = tid  # the client's transaction id
        self.utid = utid  # the id on the upstream connection (== tid unless shared)
        self.unit = unit
        self.fc = fc
        self.raw = raw  # the ADU as sent upstream
        self.link: _Link | None = None
        self.deadline: float | None = None  # loop time of its 0x0B, once armed
        self.done = False  # answered, expired or forgotten: the deadline queue skips it
        self.extended = False  # its timeout was extended once for an answer half forwarded


class _Reader(asyncio.BufferedProtocol):
    """A socket protocol that reads into the engine's one read buffer and hands
    ``data_received`` a ``bytes`` copy of exactly what was read (see
    :data:`READ_BUFFER`). The buffer is shared by every connection of the loop:
    asyncio fills it and calls :meth:`buffer_updated` in one step, in the loop's
    thread, so it is free again before the next read."""

    engine: ProxyEngine

    def get_buffer(self, sizehint: int) -> memoryview:
        return self.engine.read_buffer

    def buffer_updated(self, nbytes: int) -> None:
        self.data_received(bytes(self.engine.read_buffer[:nbytes]))

    def data_received(self, data: bytes) -> None:
        raise NotImplementedError


class _Upstream(_Reader):
    """The socket side of a :class:`_Link`."""

    def __init__(self, link: _Link) -> None:
        self.link = link
        self.engine = link.engine
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        self.link.data_received(self, data)

    def eof_received(self) -> bool:
        return False  # close: a Modbus server that half-closes is gone

    def connection_lost(self, exc: Exception | None) -> None:
        self.link.connection_lost(self, exc)


class _Link:
    """One upstream connection (a client's own, or the shared one): connects and
    reconnects with backoff, keeps the requests in flight and their timers."""

    def __init__(self, engine: ProxyEngine, owner: _Client | None) -> None:
        self.engine = engine
        self.owner = owner  # the client of a per-client link; None when shared
        self.remap = owner is None
        #: per client, to a client that takes the upstream's bytes as they come (a
        #: socket client; an RTU master's port needs whole answers to make frames)
        self.passthrough = owner is not None and takes_bytes(owner)
        self.state = "down"  # down | connecting | up | closed
        self.proto: _Upstream | None = None
        self.pending: dict[int, list[_Pending]] = {}
        self.queued: list[_Pending] = []  # waiting for the connection
        self.late: OrderedDict[int, str] = OrderedDict()  # utid -> why it is not expected
        self.next_attempt = 0.0
        self.backoff = engine.config.backoff_min
        self.failing = False
        self.decoder: MbapDecoder | None = None
        self.received = 0
        self.consumed = 0
        self.next_tid = 0
        self.last_error = ""
        self.resetting = False  # the proxy itself is aborting the connection
        #: per client: connections retired after a gateway timeout, still draining
        self.retired: list[_Link] = []
        self.parent: _Link | None = None  # of a retired connection: the client's link
        #: shared: the request whose answer is being forwarded as it comes, how many of
        #: its bytes went already, and the bytes of the incomplete answer so far
        self.streaming: _Pending | None = None
        self.streamed = 0
        self.tail = b""

    # -------------------------------------------------------------- connecting

    def connect(self) -> None:
        """Start a connection attempt (the loop's task does the waiting)."""
        if self.state in ("connecting", "up", "closed"):
            return
        self.state = "connecting"
        self.engine.loop.create_task(self._connect())

    async def _connect(self) -> None:
        engine = self.engine
        cfg = engine.config
        loop = engine.loop
        try:
            _transport, proto = await asyncio.wait_for(
                loop.create_connection(
                    lambda: _Upstream(self), cfg.upstream_host, cfg.upstream_port
                ),
                timeout=cfg.timeout,
            )
        except (TimeoutError, OSError) as exc:
            self._failed(_why(exc))
            return
        if self.state == "closed":
            if proto.transport is not None:
                proto.transport.close()
            return
        self.proto = proto  # type: ignore[assignment]
        self.state = "up"
        if proto.transport is not None:
            sock = proto.transport.get_extra_info("socket")
            if sock is not None:
                keepalive(sock)
        self.decoder = MbapDecoder(self._stream(), _S2C)
        self.received = self.consumed = 0
        self.late.clear()  # what the old connection owed can never arrive on this one
        self.streaming = None
        self.streamed = 0
        self.tail = b""
        engine.stats.upstream_connects += 1
        engine.upstream_state = "up"
        if self.failing:
            self.failing = False
            self._notice(f"upstream {cfg.upstream} is back", {"upstream": cfg.upstream})
        self.backoff = cfg.backoff_min
        queued, self.queued = self.queued, []
        out = []
        for entry in queued:
            if entry.client.closed:
                self._forget(entry)
                continue
            self._track(entry)
            out.append(entry.raw)
        if out:
            self.proto.transport.write(b"".join(out))  # type: ignore[union-attr]

    def _stream(self) -> Stream:
        owner = self.owner
        if owner is not None and owner.stream is not None:
            return owner.stream
        return Stream(-1, Transport.TCP, "proxy", self.engine.config.upstream)

    def _failed(self, why: str) -> None:
        engine = self.engine
        cfg = engine.config
        if self.state == "closed":
            return
        self.state = "down"
        engine.stats.upstream_failures += 1
        engine.upstream_state = f"unavailable ({why})"
        self.next_attempt = engine.loop.time() + self.backoff
        wait = self.backoff
        self.backoff = min(self.backoff * 2, cfg.backoff_max)
        if not self.failing or why != self.last_error:
            self._notice(
                f"upstream {cfg.upstream} unavailable ({why}): answering 0x0A, "
                f"next try in {wait:.2f} s",
                {"upstream": cfg.upstream, "reason": why},
            )
        self.failing = True
        self.last_error = why
        queued, self.queued = self.queued, []
        for entry in queued:
            self._cancel_timer(entry)
            engine.answer_exception(entry, GATEWAY_PATH_UNAVAILABLE)

    def _notice(self, message: str, info: dict[str, Any]) -> None:
        owner = self.owner
        stream = owner.stream if owner is not None else None
        self.engine.observer.event(stream, EventKind.NOTICE, {"message": message, **info})

    # -------------------------------------------------------------- requests

    def submit(self, entry: _Pending) -> bytes | None:
        """Take a request: the bytes to write upstream now, or ``None`` (queued
        for the connection, or answered 0x0A already)."""
        state = self.state
        if state == "up":
            self._track(entry)
            return entry.raw
        if state == "down" and self.engine.loop.time() >= self.next_attempt:
            self.connect()
            state = self.state
        if state == "connecting":
            self.queued.append(entry)
            self._start_timer(entry)
            return None
        self.engine.answer_exception(entry, GATEWAY_PATH_UNAVAILABLE)
        return None

    def assign_tid(self, tid: int) -> int:
        """The upstream transaction id for a client's ``tid`` (remapped when shared)."""
        if not self.remap:
            return tid
        pending, late = self.pending, self.late
        for _ in range(0x10000):
            utid = self.next_tid
            self.next_tid = (utid + 1) & 0xFFFF
            if utid not in pending and utid not in late:
                return utid
        return self.next_tid  # 65536 in flight: cannot happen with sane clients

    def _track(self, entry: _Pending) -> None:
        """``entry`` is written upstream now: wait for its answer (its timer runs
        from when it was queued, or starts now)."""
        pending = self.pending
        lst = pending.get(entry.utid)
        if lst is None:
            pending[entry.utid] = [entry]
        else:
            lst.append(entry)
        if entry.deadline is None:
            self._start_timer(entry)
        else:  # queued while connecting: its timer runs already
            entry.client.outstanding.add(entry)

    def _start_timer(self, entry: _Pending) -> None:
        """Count ``entry`` as its client's, on this link, and start its timeout."""
        entry.client.outstanding.add(entry)
        entry.link = self
        self.engine.arm(entry)

    @staticmethod
    def _cancel_timer(entry: _Pending) -> None:
        entry.done = True

    def _remove(self, entry: _Pending) -> bool:
        lst = self.pending.get(entry.utid)
        if lst is None or entry not in lst:
            return False
        lst.remove(entry)
        if not lst:
            del self.pending[entry.utid]
        return True

    def _forget(self, entry: _Pending, why: str | None = None) -> None:
        """Stop waiting for ``entry`` (its client left); a later answer is dropped."""
        self._cancel_timer(entry)
        if self._remove(entry) and why:
            self._remember_late(entry.utid, why)
        elif entry in self.queued:
            self.queued.remove(entry)

    def _remember_late(self, utid: int, why: str) -> None:
        late = self.late
        late[utid] = why
        late.move_to_end(utid)
        while len(late) > LATE_MEMORY:
            late.popitem(last=False)

    def _expire(self, entry: _Pending) -> None:
        """No answer in time: 0x0B to the client, and nothing the upstream sends for
        it later may reach the client. Per client, the upstream connection is renewed
        (:meth:`_retire`): the old one drains and drops what it owes; shared, the id
        is remembered (ids are unique on the link) and a half-received answer resets
        the link. An answer whose first bytes the client has already (forwarded as
        they came) gets one more ``timeout``; then the client is dropped, since no
        exception can go between an answer's bytes."""
        engine = self.engine
        if entry in self.queued:  # still connecting after the whole timeout
            entry.done = True
            self.queued.remove(entry)
            engine.answer_exception(entry, GATEWAY_PATH_UNAVAILABLE)
            return
        per_client = not self.remap and self.state == "up"
        if entry is self.streaming or (
            per_client
            and self.passthrough
            and self.received > self.consumed
            and entry in self.pending.get(entry.utid, ())
        ):
            held = self.received - self.consumed
            if not entry.extended:
                entry.extended = True
                engine.arm(entry)
                return
            entry.done = True
            entry.client.drop(
                f"upstream sent {held} bytes of an answer and nothing more for "
                f"{2 * engine.config.timeout:g} s (the client has them: no exception "
                "can follow)"
            )
            if entry is self.streaming:
                self.streaming = None
                self.reset("the answer being forwarded stopped half-way")
            return
        entry.done = True
        if not self._remove(entry):
            return
        holder = self._retire() if per_client else self
        holder._remember_late(entry.utid, "answered 0x0B already")
        if not entry.client.closed:
            renewed = "; upstream connection renewed" if per_client else ""
            entry.client.notice(
                f"no answer from upstream within {engine.config.timeout:g} s to tid "
                f"{entry.tid}: answered 0x0B{renewed}",
                {"tid": entry.tid, "fc": entry.fc, "unit": entry.unit},
            )
        engine.answer_exception(entry, GATEWAY_TARGET_FAILED)
        if self.state == "retired":
            self._drained()
        elif (
            self.state == "up"
            and self.remap
            and self.streaming is None  # one being forwarded has a timer of its own
            and self.received > self.consumed
        ):
            self.reset(
                f"upstream sent an incomplete answer ({self.received - self.consumed} bytes) "
                "and nothing more"
            )

    def _retire(self) -> _Link:
        """Move this client's upstream connection aside after a gateway timeout: it
        takes no new requests, its requests in flight still get their answers (or
        their own 0x0B), anything else it receives is dropped and logged, and it
        closes once it owes nothing (:data:`LINGER`). New
        requests go on a new connection (opened now), so a late answer can never
        be taken for the answer to a request that reuses its transaction id."""
        old = _Link(self.engine, self.owner)
        old.state = "retired"
        old.parent = self
        old.proto, old.decoder, old.pending = self.proto, self.decoder, self.pending
        old.received, old.consumed = self.received, self.consumed
        if old.proto is not None:
            old.proto.link = old
        for lst in old.pending.values():
            for entry in lst:
                entry.link = old
        self.retired.append(old)
        while len(self.retired) > MAX_RETIRED:
            self.retired[0].close()
        self.proto = None
        self.decoder = None
        self.pending = {}
        self.late = OrderedDict()
        self.received = self.consumed = 0
        self.state = "down"
        self.next_attempt = 0.0
        self.engine.stats.upstream_renewed += 1
        old._linger()
        self.connect()
        return old

    def _linger(self) -> None:
        """A retired connection waits for what it owes, then closes (:data:`LINGER`)."""
        self.engine.loop.call_later(LINGER * self.engine.config.timeout, self._linger_over)

    def _linger_over(self) -> None:
        if self.state != "retired":
            return
        if self.pending:
            self._linger()  # its own requests in flight expire (0x0B) first
            return
        self.close()

    def _drained(self) -> None:
        """A retired connection that owes nothing more and expects no late answer closes."""
        if not self.pending and not self.late:
            self.close()

    # -------------------------------------------------------------- answers

    def data_received(self, proto: _Upstream, data: bytes) -> None:
        if proto is not self.proto or self.decoder is None:
            return
        ts = time.time()
        self.received += len(data)
        if self.passthrough and self.state == "up":
            self._pass(data, ts)
            return
        raws = self.decoder.split_clean(data, ts)
        if raws is None:  # not whole clean ADUs: the decoder frames (or finds noise)
            self._split(data, ts)
            return
        self.consumed += len(data)
        self._route(raws, ts)

    def _split(self, data: bytes, ts: float) -> None:
        """A read that is not whole clean ADUs, on a shared (or retired) connection:
        whole ADUs are routed; of an answer still incomplete, once its transaction id
        is here, the bytes go to its client as they come (its own id put back), on
        the shared connection (a retired one forwards only whole answers)."""
        assert self.decoder is not None
        decoder = self.decoder
        raws, bad = decoder.feed_adus(data, ts)
        buf = self.tail + data if self.tail else data
        used = 0
        for raw in raws:
            used += len(raw)
        entry = self.streaming
        if raws and entry is not None:  # the answer being forwarded is complete
            first = raws.pop(0)
            self.streaming = None
            entry.done = True
            client = entry.client
            client.outstanding.discard(entry)
            self.consumed += len(first)
            self.engine.stats.responses += 1
            client.send(first[self.streamed :], ts)
            self.streamed = 0
        if raws:
            self._route(raws, ts)
        if bad is not None or not decoder.synced:
            self.tail = b""
            if bad is not None:
                self.consumed += len(bad.raw)
                self.reset(f"upstream sent bytes that are not Modbus/TCP ({bad.reason})")
            return
        tail = self.tail = buf[used:]
        if len(tail) < 2 or self.state != "up":
            return
        entry = self.streaming
        if entry is None:
            utid = (tail[0] << 8) | tail[1]
            lst = self.pending.get(utid)
            if not lst or not takes_bytes(lst[0].client):
                return  # unknown id (judged when whole), or a client that needs it whole
            entry = lst.pop(0)
            if not lst:
                del self.pending[utid]
            self.streaming = entry
            tid = entry.tid
            self.streamed = len(tail)
            entry.client.send(bytes((tid >> 8, tid & 0xFF)) + tail[2:], ts)
        elif len(tail) > self.streamed:
            part = tail[self.streamed :]
            self.streamed = len(tail)
            entry.client.send(part, ts)

    def _route(self, raws: list[bytes], ts: float) -> None:
        """Whole answers on a shared or retired connection: each to the client of its
        request (its own id put back); what cannot be routed is judged by
        :meth:`_unexpected`."""
        engine = self.engine
        outs: dict[_Client, list[bytes]] = {}
        pending = self.pending
        for raw in raws:
            self.consumed += len(raw)
            utid = (raw[0] << 8) | raw[1]
            lst = pending.get(utid)
            if lst:
                entry = lst.pop(0)
                if not lst:
                    del pending[utid]
                unchanged = False
            else:
                adopted = self._unexpected(utid, raw)
                if adopted is None:
                    continue
                entry, unchanged = adopted, True
            entry.done = True
            client = entry.client
            client.outstanding.discard(entry)
            if client.closed:
                continue
            if self.remap and not unchanged:
                tid = entry.tid
                raw = bytes((tid >> 8, tid & 0xFF)) + raw[2:]
            out = outs.get(client)
            if out is None:
                outs[client] = [raw]
            else:
                out.append(raw)
        stats = engine.stats
        for client, parts in outs.items():
            stats.responses += len(parts)
            client.send(parts[0] if len(parts) == 1 else b"".join(parts), ts)
        if self.state == "retired":
            self._drained()

    def _pass(self, data: bytes, ts: float) -> None:
        """One client's own upstream connection: the bytes go to the client as they
        came (a split answer too, before its last byte is here), unchanged, whatever
        their transaction id; framing only tells which requests are answered. Bytes
        that are not Modbus/TCP are not forwarded: the connection is reset."""
        owner = self.owner
        assert owner is not None and self.decoder is not None
        decoder = self.decoder
        raws = decoder.split_clean(data, ts)
        if raws is not None:
            self.consumed += len(data)
            self._answered(raws)
            owner.send(data, ts)
            return
        raws, bad = decoder.feed_adus(data, ts)
        for raw in raws:
            self.consumed += len(raw)
        if raws:
            self._answered(raws)
        if bad is None and decoder.synced:
            owner.send(data, ts)
            return
        # up to the end of the last whole ADU, the bytes go on; the rest never does
        upto = self.consumed - (self.received - len(data))
        if upto > 0:
            owner.send(data[:upto], ts)
        if bad is not None:
            self.consumed += len(bad.raw)
        self.reset(
            "upstream sent bytes that are not Modbus/TCP"
            + (f" ({bad.reason})" if bad is not None else "")
        )

    def _answered(self, raws: list[bytes]) -> None:
        """The answers ``raws`` go to the client (per client): their requests are no
        longer in flight. An answer whose transaction id matches no request is still
        the upstream's answer: it answers the oldest request in flight of its unit
        and function (else the oldest), which so gets no 0x0B."""
        pending = self.pending
        self.engine.stats.responses += len(raws)
        for raw in raws:
            utid = (raw[0] << 8) | raw[1]
            lst = pending.get(utid)
            if lst:
                entry = lst.pop(0)
                if not lst:
                    del pending[utid]
            else:
                entry = self._adopt(utid, raw)
                if entry is None:
                    continue
            entry.done = True
            entry.client.outstanding.discard(entry)

    def _adopt(self, utid: int, raw: bytes) -> _Pending | None:
        """An answer with an unknown transaction id, forwarded unchanged: the request
        it is taken to answer (removed from those in flight), or ``None``."""
        engine = self.engine
        engine.stats.unmatched_forwarded += 1
        unit, fc = raw[6], raw[7] & 0x7F if len(raw) > 7 else -1
        first: _Pending | None = None
        chosen: _Pending | None = None
        for lst in self.pending.values():  # in the order they were sent
            for entry in lst:
                if first is None:
                    first = entry
                if entry.unit == unit and entry.fc == fc:
                    chosen = entry
                    break
            if chosen is not None:
                break
        if chosen is None:
            chosen = first
        info: dict[str, Any] = {"tid": utid, "raw": raw.hex(" ").upper()}
        if chosen is None:
            message = (
                f"answer from upstream with tid {utid} matches no request in flight: "
                "forwarded unchanged"
            )
        else:
            self._remove(chosen)
            info["request_tid"] = chosen.tid
            message = (
                f"answer from upstream with tid {utid} matches no request's tid: "
                f"forwarded unchanged, as the answer to tid {chosen.tid}"
            )
        self._notice(message, info)
        return chosen

    def _in_flight(self) -> int:
        return sum(map(len, self.pending.values()))

    def _unexpected(self, utid: int, raw: bytes) -> _Pending | None:
        """An answer whose id is no request's on a shared or retired connection: on a
        shared one with exactly one request in flight (and not a late answer), that
        request's answer, forwarded unchanged (the request returned, its client to
        judge the id); else dropped and logged (``None``)."""
        engine = self.engine
        why = self.late.pop(utid, None)
        if why is None and self.state == "up" and len(self.pending) == 1:
            (only,) = self.pending.values()
            if len(only) == 1:
                return self._adopt(utid, raw)
        if why is not None:
            engine.stats.late_dropped += 1
            message = f"late answer from upstream (tid {utid}) dropped: {why}"
        elif self.state == "retired":
            engine.stats.late_dropped += 1
            message = (
                f"answer from upstream with tid {utid} on a connection renewed after a "
                "gateway timeout dropped: it may answer a request answered 0x0B already"
            )
        else:
            engine.stats.unmatched_dropped += 1
            which = "the shared connection" if self.remap else "this connection"
            message = (
                f"answer from upstream with unknown tid {utid} dropped: {which} "
                f"routes answers by tid ({self._in_flight()} requests in flight)"
            )
        self._notice(message, {"tid": utid, "raw": raw.hex(" ").upper()})
        return None

    def connection_lost(self, proto: _Upstream, exc: Exception | None) -> None:
        if proto is not self.proto:
            return
        self.proto = None
        self.decoder = None
        if self.state == "closed":
            return
        if self.state == "retired":
            self._detach()
            in_flight = [e for lst in self.pending.values() for e in lst]
            self.pending = {}
            if in_flight:
                self._notice(
                    f"upstream {self.engine.config.upstream} closed a renewed connection "
                    f"with {len(in_flight)} requests in flight: answered 0x0B",
                    {"upstream": self.engine.config.upstream},
                )
            for entry in in_flight:
                self._cancel_timer(entry)
                self.engine.answer_exception(entry, GATEWAY_TARGET_FAILED)
            return
        self.state = "down"
        self.next_attempt = 0.0  # a lost connection is tried again at once
        how = "rst" if exc is not None or self.resetting else "fin"
        by = "proxy" if self.resetting else "upstream"
        if by == "upstream":
            self.engine.upstream_state = f"lost ({how.upper()})"
        self.resetting = False
        # a client that has part of an answer already cannot be given an exception
        # after it: its stream cannot go on
        half = self.streaming.client if self.streaming is not None else None
        if half is None and not self.remap and self.received > self.consumed:
            half = self.owner
        held = self.received - self.consumed
        self.streaming = None
        self.tail = b""
        if half is not None:
            half.drop(
                f"the upstream connection ended after {held} bytes of an answer "
                "the client has already"
            )
        in_flight = [e for lst in self.pending.values() for e in lst]
        self.pending = {}
        if self.owner is None or not self.owner.closed:
            who = "the proxy reset" if by == "proxy" else "closed"
            self._notice(
                f"upstream {self.engine.config.upstream} {who} the connection "
                f"({how.upper()}{': ' + _why(exc) if exc else ''})"
                + (f"; {len(in_flight)} requests in flight answered 0x0B" if in_flight else ""),
                {"upstream": self.engine.config.upstream, "how": how, "by": by},
            )
        for entry in in_flight:
            self._cancel_timer(entry)
            self._remember_late(entry.utid, "the upstream connection was lost")
            self.engine.answer_exception(entry, GATEWAY_TARGET_FAILED)

    def reset(self, why: str) -> None:
        """Abort the connection (it is out of step); requests in flight get 0x0B."""
        self._notice(f"{why}: upstream connection reset", {"upstream": self.engine.config.upstream})
        proto = self.proto
        if proto is not None and proto.transport is not None:
            self.resetting = True
            proto.transport.abort()

    def write(self, data: bytes) -> None:
        proto = self.proto
        if proto is not None and proto.transport is not None:
            proto.transport.write(data)

    def _detach(self) -> None:
        """A retired connection ends: closed, and off its client's list."""
        self.state = "closed"
        parent = self.parent
        if parent is not None and self in parent.retired:
            parent.retired.remove(self)

    def close(self) -> None:
        """The owner is gone (or a retired connection is done): no reconnects, and
        the connection closes."""
        self._detach()
        for old in list(self.retired):
            old.close()
        for lst in self.pending.values():
            for entry in lst:
                self._cancel_timer(entry)
        for entry in self.queued:
            self._cancel_timer(entry)
        self.pending = {}
        self.queued = []
        proto = self.proto
        if proto is not None and proto.transport is not None:
            proto.transport.close()


class _Client(_Reader):
    """One client connection: frames its requests, guards, forwards, answers."""

    #: A client the gateway's own 0x0A/0x0B are not sent to (an RTU master, that gets
    #: silence as from an RTU slave): :meth:`ProxyEngine.answer_exception` calls
    #: :meth:`unanswered` instead.
    silent = False

    def __init__(self, engine: ProxyEngine) -> None:
        self.engine = engine
        self.transport: asyncio.Transport | None = None
        self.stream: Stream | None = None
        self.decoder: MbapDecoder | None = None
        self.link: _Link | None = None
        self.outstanding: set[_Pending] = set()
        self.closed = False
        self.half_closed = False
        self.received = 0
        self.consumed = 0
        self.partial_since: float | None = None
        self.paused_since: float | None = None
        self.drop_reason: str | None = None
        self.peer = ""
        #: the proxy's own answers to this client: ``client -> the proxy`` (made once needed)
        self.own: Stream | None = None

    # -------------------------------------------------------------- asyncio hooks

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        engine = self.engine
        self.transport = transport  # type: ignore[assignment]
        peer = transport.get_extra_info("peername") or ("?", 0)
        host, port = str(peer[0]), int(peer[1])
        self.peer = endpoint(host, port)
        if not engine.config.clients.allows(host):
            engine.stats.clients_refused += 1
            self.closed = True
            engine.observer.event(
                None,
                EventKind.GUARD,
                {
                    "message": f"refused client {self.peer}: not in --allow-from",
                    "rule": "allow-from",
                    "fc": None,
                    "unit": None,
                    "address": None,
                    "count": None,
                    "client": self.peer,
                },
            )
            transport.abort()
            return
        sock = transport.get_extra_info("socket")
        if sock is not None:
            try:  # bounded kernel buffering: a client that stops reading is seen soon
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, CLIENT_SNDBUF)
            except OSError:
                pass
            keepalive(sock)
        engine.stats.clients += 1
        engine.clients.add(self)
        self.stream = engine.observer.new_stream(Transport.TCP, self.peer, engine.config.upstream)
        self.decoder = MbapDecoder(self.stream, _C2S)
        engine.observer.event(self.stream, EventKind.CONNECT, {})
        if engine.shared is not None:
            self.link = engine.shared
            if self.link.state == "down" and engine.loop.time() >= self.link.next_attempt:
                self.link.connect()
        else:
            self.link = _Link(engine, self)
            self.link.connect()

    def data_received(self, data: bytes) -> None:
        if self.closed or self.decoder is None:
            return
        engine = self.engine
        ts = time.time()
        engine.stats.bytes_from_clients += len(data)
        self.received += len(data)
        raws = self.decoder.split_clean(data, ts)
        if raws is not None:  # whole clean ADUs: no decoding on the forwarding path
            self.consumed += len(data)
            self.partial_since = None
            self._requests(raws, ts)
            return
        raws, noise = self.decoder.feed_adus(data, ts)
        self.consumed += sum(map(len, raws))
        bad = None if noise is None else noise.reason
        if bad is None and not self.decoder.synced:
            for noise in self.decoder.flush(ts):
                bad = noise.reason
                break
            bad = bad or "not Modbus/TCP"
        if raws:
            self._requests(raws, ts)
        if bad is not None:
            self.drop(f"client sent bytes that are not Modbus/TCP ({bad})")
            return
        if self.received > self.consumed:
            if self.partial_since is None:
                self.partial_since = engine.loop.time()
        else:
            self.partial_since = None

    def _requests(self, raws: list[bytes], ts: float) -> None:
        engine = self.engine
        engine.stats.requests += len(raws)
        if not engine.config.guard.active:
            stream = self.stream
            assert stream is not None
            engine.observer.chunk(stream, _C2S, raws[0] if len(raws) == 1 else b"".join(raws), ts)
        self.forward(raws, ts)

    def forward(self, raws: list[bytes], ts: float, guarded: bool = False) -> None:
        """Guard (unless ``guarded`` already), then send ``raws`` (whole Modbus/TCP
        request ADUs, counted) upstream or queue them. Observed already when the
        guard is off or ``guarded``; else here, after the guard: what passes on the
        client's stream to the upstream, what it refuses on the proxy's own stream
        (:meth:`_refuse`: the upstream never saw it)."""
        engine = self.engine
        guard = engine.config.guard
        if guard.active and not guarded:
            passed: list[bytes] = []
            for raw in raws:
                verdict = guard.check_raw(raw[6], raw[7:])
                if verdict is None:
                    passed.append(raw)
                else:
                    self._refuse(raw, verdict.message, verdict.info, ts)
            if not passed:
                return
            raws = passed
            stream = self.stream
            assert stream is not None
            engine.observer.chunk(stream, _C2S, raws[0] if len(raws) == 1 else b"".join(raws), ts)
        link = self.link
        assert link is not None
        out: list[bytes] = []
        for raw in raws:
            tid = (raw[0] << 8) | raw[1]
            utid = link.assign_tid(tid) if link.remap else tid
            if utid != tid:
                raw = bytes((utid >> 8, utid & 0xFF)) + raw[2:]
            data = link.submit(_Pending(self, tid, utid, raw[6], raw[7], raw))
            if data is not None:
                out.append(data)
        if out:
            link.write(out[0] if len(out) == 1 else b"".join(out))

    def _refuse(self, raw: bytes, message: str, info: Any, ts: float) -> None:
        """Answer the request ADU ``raw`` with the guard's exception, and audit it. A
        socket client's refused request and its answer are observed on the proxy's
        own stream (:meth:`send_own`), where they paired: the upstream never saw it."""
        engine = self.engine
        code = engine.config.guard.exception_code
        engine.stats.guard_refusals += 1
        adu = encode_adu((raw[0] << 8) | raw[1], raw[6], encode_exception(raw[7], code))
        if takes_bytes(self) and self.transport is not None and not self.closed:
            engine.observer.chunk(self._own_stream(), _C2S, raw, ts)
        self.send_own(adu, ts)
        engine.observer.event(
            self.stream,
            EventKind.GUARD,
            {"message": message, **info, "client": self.peer, "exception": code},
            ts,
        )

    def eof_received(self) -> bool:
        if self.outstanding:
            self.half_closed = True
            self.notice(
                f"client half-closed with {len(self.outstanding)} requests in flight; "
                "answering them first",
                {},
            )
            return True
        return False

    def pause_writing(self) -> None:
        self.paused_since = self.engine.loop.time()
        if self.transport is not None:
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        self.paused_since = None
        if self.transport is not None and not self.closed:
            self.transport.resume_reading()

    def connection_lost(self, exc: Exception | None) -> None:
        if self.stream is None:  # refused at accept
            return
        engine = self.engine
        was_closed = self.closed
        self.closed = True
        engine.clients.discard(self)
        if was_closed and self.drop_reason is None:
            return
        link = self.link
        left = len(self.outstanding)
        if link is not None:
            for entry in list(self.outstanding):
                (entry.link or link)._forget(entry, "its client left")
            if link.owner is self:
                link.close()
        self.outstanding.clear()
        if self.drop_reason is not None:
            info: dict[str, Any] = {"how": "rst", "by": "proxy", "reason": self.drop_reason}
        else:
            info = {"how": "rst" if exc is not None else "fin", "by": "client"}
            if exc is not None:
                info["reason"] = _why(exc)
        if left:
            info["unanswered"] = left
        engine.observer.event(self.stream, EventKind.DISCONNECT, info)

    # -------------------------------------------------------------- helpers

    def send(self, data: bytes, ts: float) -> None:
        """Write ``data`` (whole ADUs) to the client, then give the hub a copy."""
        transport = self.transport
        if transport is None or self.closed:
            return
        transport.write(data)
        engine = self.engine
        engine.stats.bytes_to_clients += len(data)
        assert self.stream is not None
        engine.observer.chunk(self.stream, _S2C, data, ts)
        if self.half_closed and not self.outstanding:
            self.closed = True
            self.drop_reason = None
            transport.close()
            self._finish_half_closed()

    def send_own(self, data: bytes, ts: float) -> None:
        """An answer the proxy made itself (0x0A, 0x0B, a guard refusal): to the client
        like any answer, observed on the proxy's own stream, ``client -> the proxy's
        listening endpoint`` (its source is the proxy, not the server): no log,
        screen or export shows it as sent by the server. A subclass that writes
        answers its own way (an RTU master's port) gets it through its ``send``."""
        if not takes_bytes(self):
            self.send(data, ts)
            return
        transport = self.transport
        if transport is None or self.closed:
            return
        transport.write(data)
        engine = self.engine
        engine.stats.bytes_to_clients += len(data)
        engine.observer.chunk(self._own_stream(), _S2C, data, ts)
        if self.half_closed and not self.outstanding:
            self.closed = True
            self.drop_reason = None
            transport.close()
            self._finish_half_closed()

    def _own_stream(self) -> Stream:
        own = self.own
        if own is None:
            engine = self.engine
            own = self.own = engine.observer.new_stream(Transport.TCP, self.peer, engine.name)
        return own

    def _finish_half_closed(self) -> None:
        engine = self.engine
        engine.clients.discard(self)
        link = self.link
        if link is not None and link.owner is self:
            link.close()
        engine.observer.event(self.stream, EventKind.DISCONNECT, {"how": "fin", "by": "client"})

    def notice(self, message: str, info: dict[str, Any]) -> None:
        self.engine.observer.event(self.stream, EventKind.NOTICE, {"message": message, **info})

    def unanswered(self, entry: _Pending, code: int) -> None:
        """A silent client's request the gateway cannot answer (``code`` 0x0A/0x0B)."""

    def drop(self, reason: str, count: bool = True) -> None:
        """Disconnect this client (reset), with ``reason`` in the log."""
        if self.closed:
            return
        if count:
            self.engine.stats.clients_dropped += 1
        self.drop_reason = reason
        self.closed = True
        self.notice(f"client {self.peer} dropped: {reason}", {"client": self.peer})
        if self.transport is not None:
            self.transport.abort()


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
        self.clients: set[_Client] = set()
        self.shared: Any = None  # the shared _Link, or the upstream factory's link
        self.loop: asyncio.AbstractEventLoop = None  # type: ignore[assignment]
        self.address: tuple[str, int] | None = None
        #: the proxy as an endpoint (its listening address): the server side of the
        #: streams of its own answers (:meth:`_Client.send_own`)
        self.name = "proxy"
        self._server: asyncio.base_events.Server | None = None
        self._stop: asyncio.Event | None = None
        #: requests waiting for their answer, in deadline order (one timeout for all)
        self._deadlines: deque[_Pending] = deque()
        self._expiry: asyncio.TimerHandle | None = None
        #: the upstream as last seen (for the live monitor): up, unavailable (why), ...
        self.upstream_state = "not connected yet"
        #: every socket of the loop reads into this, one read at a time (:class:`_Reader`)
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

    def arm(self, entry: _Pending) -> None:
        """Start ``entry``'s timeout: one loop timer serves every request, since all
        share one timeout and so expire in the order they were sent."""
        loop = self.loop
        entry.deadline = deadline = loop.time() + self.config.timeout
        self._deadlines.append(entry)
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
            if entry.link is not None:
                entry.link._expire(entry)
            else:
                entry.done = True
        while dq and dq[0].done:
            dq.popleft()
        if dq and dq[0].deadline is not None:
            self._expiry = self.loop.call_at(dq[0].deadline, self._expire_due)

    def answer_exception(self, entry: _Pending, code: int) -> None:
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
            encode_adu(entry.tid, entry.unit, encode_exception(entry.fc, code)), time.time()
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
                self.shared = _Link(self, None)
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
                lambda: _Client(self),
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
                if since is not None and now - since > timeout:
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


class ProxyThread:
    """Runs a :class:`ProxyEngine` on its own asyncio loop in its own thread.

    :meth:`start` returns once the listening socket is bound (or raises the
    ``OSError`` that prevented it); :meth:`stop` is safe from any thread and
    from signal handlers; ``on_exit`` runs in the engine's thread when the loop
    has ended (the command stops the hub there).
    """

    def __init__(self, engine: ProxyEngine, on_exit: Callable[[], None] | None = None) -> None:
        self.engine = engine
        self._on_exit = on_exit
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=self._main, name="mbmon-proxy", daemon=True)

    def start(self) -> tuple[str, int]:
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise self._error
        assert self.engine.address is not None
        return self.engine.address

    def _main(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            try:
                loop.run_until_complete(self.engine.start())
            except BaseException as exc:
                self._error = exc
                return
            finally:
                self._ready.set()
            loop.run_until_complete(self.engine.serve())
        finally:
            try:
                for task in asyncio.all_tasks(loop):
                    task.cancel()
                loop.run_until_complete(asyncio.sleep(0))
                loop.close()
            finally:
                self.engine.observer.flush()
                if self._on_exit is not None:
                    self._on_exit()

    def stop(self) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self.engine.request_stop)
            except RuntimeError:  # closed in between
                pass

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the thread; whether it has ended."""
        self._thread.join(timeout)
        return not self._thread.is_alive()


def takes_bytes(client: _Client) -> bool:
    """Whether ``client`` takes an answer's bytes as they come (a socket client),
    not only whole answers (a subclass with its own ``send``: an RTU master's port)."""
    return type(client).send is _Client.send


def keepalive(sock: Any) -> None:
    """Turn TCP keepalive on for ``sock`` (see :data:`KEEPALIVE_IDLE`); where the
    platform lacks the per-socket timings, its defaults apply."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    except OSError:
        return
    for name, value in (
        ("TCP_KEEPIDLE", KEEPALIVE_IDLE),
        ("TCP_KEEPINTVL", KEEPALIVE_INTERVAL),
        ("TCP_KEEPCNT", KEEPALIVE_COUNT),
    ):
        option = getattr(socket, name, None)
        if option is not None:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, option, value)
            except OSError:
                pass


def _why(exc: BaseException | None) -> str:
    """Short words for a connection error."""
    if exc is None:
        return ""
    if isinstance(exc, TimeoutError):
        return "connect timed out"
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused"
    if isinstance(exc, ConnectionResetError):
        return "connection reset"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__
