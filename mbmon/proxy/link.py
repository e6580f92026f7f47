"""An upstream link's state and its answer path: :class:`Pending` (one request in
flight), :class:`Link` (what the engine and its clients ask of any upstream link:
a TCP server's, :class:`~mbmon.proxy.upstream.TcpLink`, or an RTU bus's,
:class:`~mbmon.proxy.serial.RtuLink`), and :class:`LinkBase`, the requests in
flight of one upstream connection and how its answers reach their clients: as
their bytes come (one client's own connection, transaction ids untouched), or
whole and routed by transaction id (the shared connection, ids remapped; a
connection retired after a gateway timeout). Connecting, timeouts and renewal
are :class:`~mbmon.proxy.upstream.TcpLink`'s.
"""

from __future__ import annotations

import asyncio
import time
from collections import OrderedDict
from typing import Any, Protocol

from mbmon.model import Direction, EventKind, Stream, Transport
from mbmon.protocol.mbap import MbapDecoder
from mbmon.proxy.config import ProxyConfig, ProxyStats
from mbmon.proxy.observer import Observer
from mbmon.proxy.reader import Reader

__all__ = [
    "LATE_MEMORY",
    "Link",
    "LinkBase",
    "LinkClient",
    "LinkEngine",
    "Pending",
    "UpstreamSocket",
]

#: How many answered-with-0x0B (or orphaned) upstream transaction ids are remembered,
#: so that their late answers are recognised and dropped.
LATE_MEMORY = 4096

_S2C = Direction.S2C


class LinkClient(Protocol):
    """What a link asks of a client (:class:`~mbmon.proxy.client.Client` is one):
    its stream, whether it is gone, its requests in flight, whether it takes an
    answer's bytes as they come and whether it has part of one (``midway``);
    :meth:`send` gives it whole answers, :meth:`stream_part` the bytes of the
    answers being forwarded as they come, :meth:`send_own` an answer the proxy made itself,
    :meth:`flush` lets go the answers it holds once a request left ``outstanding``
    with no answer written, :meth:`unanswered` tells a silent client's request went
    unanswered, :meth:`drop` disconnects it, :meth:`notice` logs about it."""

    stream: Stream | None
    closed: bool
    silent: bool
    streams_answers: bool
    midway: bool
    outstanding: set[Pending]

    def send(self, data: bytes, ts: float) -> None: ...

    def stream_part(self, data: bytes, ts: float, midway: bool) -> None: ...

    def flush(self) -> None: ...

    def drop(self, reason: str, count: bool = True) -> None: ...

    def notice(self, message: str, info: dict[str, Any]) -> None: ...

    def send_own(self, data: bytes, ts: float, seq: int = 0) -> None: ...

    def unanswered(self, entry: Pending, code: int) -> None: ...


class LinkEngine(Protocol):
    """What a link (and a client) asks of the engine
    (:class:`~mbmon.proxy.engine.ProxyEngine` is it): its settings, counters,
    observer, loop and read buffer; :meth:`arm` starts a request's timeout,
    :meth:`answer_exception` answers a request with a gateway exception."""

    config: ProxyConfig
    stats: ProxyStats
    observer: Observer
    loop: asyncio.AbstractEventLoop
    upstream_state: str
    read_buffer: memoryview

    def arm(self, entry: Pending) -> None: ...

    def answer_exception(self, entry: Pending, code: int) -> None: ...


class Link(Protocol):
    """What the engine and its clients ask of an upstream link (the contract a new
    kind of upstream implements; :class:`~mbmon.proxy.upstream.TcpLink` and
    :class:`~mbmon.proxy.serial.RtuLink` do).

    ``owner`` is the one client of a per-client link (``None``: shared by every
    client); ``remap`` whether transaction ids are remapped on it (then
    :meth:`assign_tid` gives the upstream's id); ``state`` is ``down``,
    ``connecting``, ``up``, ``retired`` or ``closed``; ``next_attempt`` the loop time
    before which a down link is not retried. :meth:`submit` takes a request (the
    bytes to write now, or ``None``: queued, or answered by the gateway already);
    :meth:`forget` stops waiting for one (its client left; a later answer is
    dropped, and logged with ``why``); :meth:`close` ends the link for good.
    """

    owner: LinkClient | None
    remap: bool
    next_attempt: float

    @property
    def state(self) -> str: ...

    def connect(self) -> None: ...

    def assign_tid(self, tid: int) -> int: ...

    def submit(self, entry: Pending) -> bytes | None: ...

    def write(self, data: bytes) -> None: ...

    def forget(self, entry: Pending, why: str | None = None) -> None: ...

    def close(self) -> None: ...


class Pending:
    """One request in flight upstream."""

    __slots__ = (
        "client",
        "deadline",
        "done",
        "extended",
        "fc",
        "link",
        "raw",
        "seq",
        "tid",
        "unit",
        "utid",
    )

    def __init__(
        self, client: LinkClient, tid: int, utid: int, unit: int, fc: int, raw: bytes, seq: int = 0
    ):
        self.client = client
        self.tid = tid  # the client's transaction id
        self.utid = utid  # the id on the upstream connection (== tid unless shared)
        self.unit = unit
        self.fc = fc
        self.raw = raw  # the ADU as sent upstream
        self.seq = seq  # its place among its client's requests (their answers' order)
        self.link: Link | None = None
        self.deadline: float | None = None  # loop time of its 0x0B, once armed
        self.done = False  # answered, expired or forgotten: the deadline queue skips it
        self.extended = False  # its timeout was extended once for an answer half forwarded


class UpstreamSocket(Reader):
    """The socket side of a :class:`LinkBase`."""

    engine: LinkEngine

    def __init__(self, link: LinkBase) -> None:
        self.link = link
        self.engine = link.engine
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def buffer_updated(self, nbytes: int) -> None:
        # Reader's, one call less: every answer
        self.link.data_received(self, bytes(self.engine.read_buffer[:nbytes]))

    def data_received(self, data: bytes) -> None:
        self.link.data_received(self, data)

    def eof_received(self) -> bool:
        return False  # close: a Modbus server that half-closes is gone

    def connection_lost(self, exc: Exception | None) -> None:
        self.link.connection_lost(self, exc)


class LinkBase:
    """One upstream connection's state, its requests in flight and its answer path
    (see the module text); a subclass connects it and times its requests out
    (:class:`~mbmon.proxy.upstream.TcpLink`)."""

    def __init__(self, engine: LinkEngine, owner: LinkClient | None) -> None:
        self.engine = engine
        self.owner = owner  # the client of a per-client link; None when shared
        self.remap = owner is None
        #: per client, to a client that takes the upstream's bytes as they come (a
        #: socket client; an RTU master's port needs whole answers to make frames)
        self.passthrough = owner is not None and owner.streams_answers
        self.state = "down"  # down | connecting | up | closed
        self.proto: UpstreamSocket | None = None
        self.pending: dict[int, list[Pending]] = {}
        self.queued: list[Pending] = []  # waiting for the connection
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
        self.retired: list[LinkBase] = []
        self.parent: LinkBase | None = None  # of a retired connection: the client's link
        #: shared: the request whose answer is being forwarded as it comes, how many of
        #: its bytes went already, and the bytes of the incomplete answer so far
        self.streaming: Pending | None = None
        self.streamed = 0
        self.tail = b""

    def decoding_stream(self) -> Stream:
        """The stream the answers' decoder stamps its frames with (never observed)."""
        owner = self.owner
        if owner is not None and owner.stream is not None:
            return owner.stream
        return Stream(-1, Transport.TCP, "proxy", self.engine.config.upstream)

    def notice(self, message: str, info: dict[str, Any]) -> None:
        owner = self.owner
        stream = owner.stream if owner is not None else None
        self.engine.observer.event(stream, EventKind.NOTICE, {"message": message, **info})

    def remove(self, entry: Pending) -> bool:
        lst = self.pending.get(entry.utid)
        if lst is None or entry not in lst:
            return False
        lst.remove(entry)
        if not lst:
            del self.pending[entry.utid]
        return True

    def remember_late(self, utid: int, why: str) -> None:
        late = self.late
        late[utid] = why
        late.move_to_end(utid)
        while len(late) > LATE_MEMORY:
            late.popitem(last=False)

    def drained(self) -> None:
        """A retired connection that owes nothing more and expects no late answer closes."""
        if not self.pending and not self.late:
            self.close()

    # -------------------------------------------------------------- answers

    def data_received(self, proto: UpstreamSocket, data: bytes) -> None:
        if proto is not self.proto or self.decoder is None:
            return
        ts = time.time()
        self.received += len(data)
        if self.passthrough and self.state == "up":
            owner = self.owner
            raws = self.decoder.split_clean(data, ts)
            if raws is None or len(raws) != 1 or owner is None:
                self._pass(data, ts, raws)
                return
            # one whole clean answer, the common case: _pass and _answered inline
            raw = raws[0]
            self.consumed += len(data)
            self.engine.stats.responses += 1
            pending = self.pending
            utid = (raw[0] << 8) | raw[1]
            lst = pending.get(utid)
            entry: Pending | None
            if lst:
                entry = lst.pop(0)
                if not lst:
                    del pending[utid]
            else:
                entry = self._adopt(utid, raw)
            if entry is not None:
                entry.done = True
                entry.client.outstanding.discard(entry)
            owner.stream_part(data, ts, False)
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
            self.streamed, done = 0, self.streamed
            client.stream_part(first[done:], ts, False)
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
            if not lst or not lst[0].client.streams_answers:
                return  # unknown id (judged when whole), or a client that needs it whole
            entry = lst.pop(0)
            if not lst:
                del self.pending[utid]
            self.streaming = entry
            tid = entry.tid
            self.streamed = len(tail)
            entry.client.stream_part(bytes((tid >> 8, tid & 0xFF)) + tail[2:], ts, True)
        elif len(tail) > self.streamed:
            part = tail[self.streamed :]
            self.streamed = len(tail)
            entry.client.stream_part(part, ts, True)

    def _route(self, raws: list[bytes], ts: float) -> None:
        """Whole answers on a shared or retired connection: each to the client of its
        request (its own id put back); what cannot be routed is judged by
        :meth:`_unexpected`."""
        engine = self.engine
        outs: dict[LinkClient, list[bytes]] = {}
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
            self.drained()

    def _pass(self, data: bytes, ts: float, raws: list[bytes] | None) -> None:
        """One client's own upstream connection: the bytes go to the client as they
        came (a split answer too, before its last byte is here), unchanged, whatever
        their transaction id; framing only tells which requests are answered. Bytes
        that are not Modbus/TCP are not forwarded: the connection is reset. ``raws``:
        what the decoder's ``split_clean`` made of ``data``."""
        owner = self.owner
        assert owner is not None and self.decoder is not None
        decoder = self.decoder
        if raws is not None:
            self.consumed += len(data)
            self._answered(raws)
            owner.stream_part(data, ts, False)
            return
        raws, bad = decoder.feed_adus(data, ts)
        for raw in raws:
            self.consumed += len(raw)
        if raws:
            self._answered(raws)
        if bad is None and decoder.synced:
            owner.stream_part(data, ts, self.received > self.consumed)
            return
        # up to the end of the last whole ADU, the bytes go on; the rest never does
        upto = self.consumed - (self.received - len(data))
        if upto > 0:
            owner.stream_part(data[:upto], ts, False)
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
            entry: Pending | None
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

    def _adopt(self, utid: int, raw: bytes) -> Pending | None:
        """An answer with an unknown transaction id, forwarded unchanged: the request
        it is taken to answer (removed from those in flight), or ``None``."""
        engine = self.engine
        engine.stats.unmatched_forwarded += 1
        unit, fc = raw[6], raw[7] & 0x7F if len(raw) > 7 else -1
        first: Pending | None = None
        chosen: Pending | None = None
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
            self.remove(chosen)
            info["request_tid"] = chosen.tid
            message = (
                f"answer from upstream with tid {utid} matches no request's tid: "
                f"forwarded unchanged, as the answer to tid {chosen.tid}"
            )
        self.notice(message, info)
        return chosen

    def in_flight(self) -> int:
        return sum(map(len, self.pending.values()))

    def _unexpected(self, utid: int, raw: bytes) -> Pending | None:
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
                f"routes answers by tid ({self.in_flight()} requests in flight)"
            )
        self.notice(message, {"tid": utid, "raw": raw.hex(" ").upper()})
        return None

    def reset(self, why: str) -> None:
        """Abort the connection (it is out of step); requests in flight get 0x0B."""
        self.notice(f"{why}: upstream connection reset", {"upstream": self.engine.config.upstream})
        proto = self.proto
        if proto is not None and proto.transport is not None:
            self.resetting = True
            proto.transport.abort()

    def connection_lost(self, proto: UpstreamSocket, exc: Exception | None) -> None:
        """The connection ended (the subclass's: it decides what follows)."""
        raise NotImplementedError

    def close(self) -> None:
        """End the link (the subclass's: it owns the connection)."""
        raise NotImplementedError
