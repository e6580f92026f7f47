"""The client side: :class:`Client`, one client connection of the engine. It frames
the client's requests (:class:`~mbmon.protocol.mbap.MbapDecoder`), has the guard
judge them, forwards what passes to its upstream link and writes the answers
back, observed after the forwarding. It drops a client whose bytes are not
Modbus/TCP, that stays half-way through a request or that does not read.

Answers reach the client whole: the upstream's bytes go on as they come
(:meth:`Client.stream_part`), and while the client has part of an answer
(``midway``) nothing else is written to it: an answer the proxy made (a guard
refusal, 0x0A, 0x0B) or a whole one from another upstream connection waits until
that answer is whole. An answer the proxy made also keeps its request's place:
it waits until every earlier request of the client is answered.

A subclass may take the client's place on another medium (an RTU master's serial
port, :class:`~mbmon.proxy.serial.RtuFront`): it sets :attr:`Client.silent` (no
gateway exception is sent to it; :meth:`Client.unanswered` says why instead) and
:attr:`Client.streams_answers` (``False``: it gets whole answers through
:meth:`Client.send`, never their bytes as they come), and writes answers its own
way by overriding :meth:`Client.send`.
"""

from __future__ import annotations

import asyncio
import socket
import time
from bisect import insort
from typing import Any, Protocol, cast

from mbmon.model import Direction, EventKind, Noise, Stream, Transport
from mbmon.protocol.mbap import MbapDecoder, encode_adu
from mbmon.protocol.pdu import encode_exception
from mbmon.proxy.config import endpoint
from mbmon.proxy.guard import Verdict
from mbmon.proxy.keepalive import connection_error, keepalive
from mbmon.proxy.link import Link, LinkEngine, Pending
from mbmon.proxy.reader import Reader
from mbmon.proxy.upstream import TcpLink

__all__ = ["CLIENT_SNDBUF", "HOLD_LIMIT", "MADE_BY_PROXY", "Client", "ClientEngine"]

#: The kernel send buffer of a client socket (the kernel doubles it): Modbus answers
#: are at most 260 bytes, so this holds hundreds; a client that leaves more unread
#: than this and the loop's 64 KiB is not reading, and is dropped after ``timeout``.
CLIENT_SNDBUF = 64 * 1024

#: Bytes of answers a client may have waiting for their turn (:meth:`Client.send_own`)
#: before the proxy stops reading its requests, until no more than half as many wait:
#: a client that pipelines refused writes behind a slow answer cannot grow the
#: proxy's memory.
HOLD_LIMIT = 64 * 1024

#: The note on an answer the proxy made itself (0x0A, 0x0B, a guard refusal): the
#: pipeline puts it on every answer of the proxy's own stream (the client's CONNECT
#: names that stream, ``answers_on``, and the note).
MADE_BY_PROXY = "made by the proxy"

_C2S = Direction.C2S
_S2C = Direction.S2C


class ClientEngine(LinkEngine, Protocol):
    """What a client asks of the engine besides a link's needs: the set of its
    clients, the shared link (``None``: one per client) and its own name (the
    listening endpoint)."""

    clients: set[Client]
    shared: Link | None
    name: str


class Client(Reader):
    """One client connection: frames its requests, guards, forwards, answers."""

    #: A client the gateway's own 0x0A/0x0B are not sent to (an RTU master, that gets
    #: silence as from an RTU slave): :meth:`ProxyEngine.answer_exception` calls
    #: :meth:`unanswered` instead.
    silent = False
    engine: ClientEngine

    #: Whether the client takes an answer's bytes as they come (a socket client); a
    #: subclass that needs whole answers (to make frames of them) sets ``False`` and
    #: gets them through its own :meth:`send`.
    streams_answers = True

    def __init__(self, engine: ClientEngine) -> None:
        self.engine = engine
        self.transport: asyncio.Transport | None = None
        self.stream: Stream | None = None
        self.decoder: MbapDecoder | None = None
        self.link: Link | None = None
        self.outstanding: set[Pending] = set()
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
        #: the client has part of an answer (its bytes forwarded as they came): nothing
        #: else may be written to it until the rest of that answer
        self.midway = False
        #: the place of the client's last request (:attr:`Pending.seq`)
        self.seq = 0
        #: answers the proxy made, waiting for their turn: (seq, order, bytes)
        self.held: list[tuple[int, int, bytes]] = []
        #: whole answers of another upstream connection, waiting for the one midway
        self.waiting: list[bytes] = []
        self.held_bytes = 0
        self._order = 0
        self.hold_paused = False  # reading paused: too many answers waiting

    # -------------------------------------------------------------- asyncio hooks

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        engine = self.engine
        self.transport = tcp = cast(asyncio.Transport, transport)
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
            tcp.abort()
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
        observer = engine.observer
        self.stream = observer.new_stream(Transport.TCP, self.peer, engine.config.upstream)
        self.own = observer.new_stream(Transport.TCP, self.peer, engine.name)
        self.decoder = MbapDecoder(self.stream, _C2S)
        # the proxy's own answers to this client go on a stream of their own (their
        # source is the proxy) and pair with the requests of this one
        info = {"answers_on": self.own.id, "note": MADE_BY_PROXY}
        observer.event(self.stream, EventKind.CONNECT, info)
        if engine.shared is not None:
            self.link = engine.shared
            if self.link.state == "down" and engine.loop.time() >= self.link.next_attempt:
                self.link.connect()
        else:
            self.link = TcpLink(engine, self)
            self.link.connect()

    def buffer_updated(self, nbytes: int) -> None:
        """A read of the client's socket (in the loop's one buffer): the common case,
        one whole clean request ADU with the guard off and a client's own upstream
        connection (ids not remapped), framed, observed and forwarded here in one
        step (about half the forwarding process's Python calls a request: its CPU
        a request is what the proxy adds to a round trip, docs/performance.md);
        anything else goes the general way (:meth:`data_received`), which does the
        same to the same bytes."""
        engine = self.engine
        data = bytes(engine.read_buffer[:nbytes])
        decoder = self.decoder
        if self.closed or decoder is None:
            return
        ts = time.time()
        raws = decoder.split_clean(data, ts)
        link = self.link
        if (
            raws is None
            or len(raws) != 1
            or engine.config.guard.active
            or link is None
            or link.remap
        ):
            self._received(data, ts, raws)
            return
        stats = engine.stats
        stats.bytes_from_clients += nbytes
        self.received += nbytes
        self.consumed += nbytes
        self.partial_since = None
        stats.requests += 1
        stream = self.stream
        assert stream is not None
        engine.observer.chunk(stream, _C2S, data, ts)
        self.seq = seq = self.seq + 1
        tid = (data[0] << 8) | data[1]
        out = link.submit(Pending(self, tid, tid, data[6], data[7], data, seq))
        if out is not None:
            link.write(out)

    def data_received(self, data: bytes) -> None:
        if self.closed or self.decoder is None:
            return
        ts = time.time()
        self._received(data, ts, self.decoder.split_clean(data, ts))

    def _received(self, data: bytes, ts: float, raws: list[bytes] | None) -> None:
        """The client's bytes ``data`` (read at ``ts``; ``raws``: what the decoder's
        ``split_clean`` made of them): framed, guarded, observed and forwarded; a
        client whose bytes are not Modbus/TCP is dropped."""
        engine = self.engine
        assert self.decoder is not None
        engine.stats.bytes_from_clients += len(data)
        self.received += len(data)
        if raws is not None:  # whole clean ADUs: no decoding on the forwarding path
            self.consumed += len(data)
            self.partial_since = None
            self._requests(raws, ts)
            return
        raws, noise = self.decoder.feed_adus(data, ts)
        self.consumed += sum(map(len, raws))
        bad = None if noise is None else noise.reason
        if bad is None and not self.decoder.synced:
            for item in self.decoder.flush(ts):
                bad = item.reason if isinstance(item, Noise) else None
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
        (:meth:`refuse`: the upstream never saw it)."""
        engine = self.engine
        guard = engine.config.guard
        seq = self.seq
        self.seq = seq + len(raws)
        refused: list[tuple[bytes, Verdict, int]] = []
        places: list[int] | None = None
        if guard.active and not guarded:
            passed: list[bytes] = []
            places = []
            for raw in raws:
                seq += 1
                verdict = guard.check_raw(raw[6], raw[7:])
                if verdict is None:
                    passed.append(raw)
                    places.append(seq)
                else:
                    refused.append((raw, verdict, seq))
            raws = passed
            if raws:
                stream = self.stream
                assert stream is not None
                joined = raws[0] if len(raws) == 1 else b"".join(raws)
                engine.observer.chunk(stream, _C2S, joined, ts)
        link = self.link
        assert link is not None
        out: list[bytes] = []
        for i, raw in enumerate(raws):
            tid = (raw[0] << 8) | raw[1]
            utid = link.assign_tid(tid) if link.remap else tid
            if utid != tid:
                raw = bytes((utid >> 8, utid & 0xFF)) + raw[2:]
            place = places[i] if places is not None else seq + i + 1
            data = link.submit(Pending(self, tid, utid, raw[6], raw[7], raw, place))
            if data is not None:
                out.append(data)
        if out:
            link.write(out[0] if len(out) == 1 else b"".join(out))
        # refusals after the requests before them are in flight: they wait their turn
        for raw, verdict, place in refused:
            self.refuse(raw, verdict.message, verdict.info, ts, place)

    def refuse(self, raw: bytes, message: str, info: Any, ts: float, seq: int = 0) -> None:
        """Answer the request ADU ``raw`` (the client's request number ``seq``) with
        the guard's exception, and audit it. A socket client's refused request and its
        answer are observed on the proxy's own stream (:meth:`send_own`): the upstream
        never saw it."""
        engine = self.engine
        code = engine.config.guard.exception_code
        engine.stats.guard_refusals += 1
        adu = encode_adu((raw[0] << 8) | raw[1], raw[6], encode_exception(raw[7], code))
        if self.streams_answers and self.transport is not None and not self.closed:
            engine.observer.chunk(self._own_stream(ts), _C2S, raw, ts)
        self.send_own(adu, ts, seq)
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
        if self.transport is not None and not self.closed and not self.hold_paused:
            self._resume_reading()

    def _resume_reading(self) -> None:
        """Read the client again; a request it was half-way through when the proxy
        stopped reading has its full ``timeout`` again from now."""
        if self.partial_since is not None:
            self.partial_since = self.engine.loop.time()
        assert self.transport is not None
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
                (entry.link or link).forget(entry, "its client left")
            if link.owner is self:
                link.close()
        self.outstanding.clear()
        self._forget_held()
        if self.drop_reason is not None:
            info: dict[str, Any] = {"how": "rst", "by": "proxy", "reason": self.drop_reason}
        else:
            info = {"how": "rst" if exc is not None else "fin", "by": "client"}
            if exc is not None:
                info["reason"] = connection_error(exc)
        if left:
            info["unanswered"] = left
        engine.observer.event(self.stream, EventKind.DISCONNECT, info)

    # -------------------------------------------------------------- helpers

    def send(self, data: bytes, ts: float) -> None:
        """Write ``data`` (whole answers of the upstream's) to the client, then give the
        hub a copy; while the client has part of another answer, after that one."""
        transport = self.transport
        if transport is None or self.closed:
            return
        if self.midway:
            self.waiting.append(data)
            return
        transport.write(data)
        engine = self.engine
        engine.stats.bytes_to_clients += len(data)
        assert self.stream is not None
        engine.observer.chunk(self.stream, _S2C, data, ts)
        if self.held:
            self.flush()
        if self.half_closed:
            self._close_when_done()

    def stream_part(self, data: bytes, ts: float, midway: bool) -> None:
        """Write ``data``, bytes of the upstream's answers forwarded as they come, then
        give the hub a copy; ``midway``: they end inside an answer, and nothing else
        may be written to the client until its rest (then what waited goes)."""
        transport = self.transport
        if transport is None or self.closed:
            return
        transport.write(data)
        self.midway = midway
        engine = self.engine
        engine.stats.bytes_to_clients += len(data)
        assert self.stream is not None
        engine.observer.chunk(self.stream, _S2C, data, ts)
        if midway:
            return
        if self.held or self.waiting:
            self.flush()
        if self.half_closed:
            self._close_when_done()

    def send_own(self, data: bytes, ts: float, seq: int = 0) -> None:
        """An answer the proxy made itself (0x0A, 0x0B, a guard refusal) to the
        client's request number ``seq``: to the client like any answer, observed on
        the proxy's own stream, ``client -> the proxy's listening endpoint`` (its
        source is the proxy, not the server): no log, screen or export shows it as
        sent by the server. It keeps its request's place: while the client has part
        of an answer, or an earlier request of it is still in flight, it waits
        (:meth:`flush` writes it when its turn comes). A subclass that writes answers
        its own way (an RTU master's port) gets it through its ``send``."""
        if not self.streams_answers:
            self.send(data, ts)
            return
        if self.transport is None or self.closed:
            return
        if self.midway or self.held or self._before(seq):
            self._order += 1
            insort(self.held, (seq, self._order, data))
            self.held_bytes += len(data)
            if self.held_bytes > HOLD_LIMIT and not self.hold_paused:
                self.hold_paused = True
                self.transport.pause_reading()
            self.flush()
            return
        self._write_own(data, ts)
        if self.half_closed:
            self._close_when_done()

    def _before(self, seq: int) -> bool:
        """Whether a request before the client's request number ``seq`` still waits
        for its answer (one given up on, ``done``, never gets one: it holds nothing)."""
        for entry in self.outstanding:
            if entry.seq < seq and not entry.done:
                return True
        return False

    def flush(self) -> None:
        """Write the answers that waited and whose turn it is: none while the client
        has part of an answer; then the upstream's whole answers that waited for it,
        then the proxy's own, in the order of their requests, each once every earlier
        request is answered."""
        transport = self.transport
        if self.midway or transport is None or self.closed:
            return
        engine = self.engine
        now = time.time()
        if self.waiting:
            waiting, self.waiting = self.waiting, []
            data = waiting[0] if len(waiting) == 1 else b"".join(waiting)
            transport.write(data)
            engine.stats.bytes_to_clients += len(data)
            assert self.stream is not None
            engine.observer.chunk(self.stream, _S2C, data, now)
        held = self.held
        if held:
            low = min((e.seq for e in self.outstanding if not e.done), default=None)
            n = 0
            for seq, _order, data in held:
                if low is not None and low < seq:
                    break
                self._write_own(data, now)
                self.held_bytes -= len(data)
                n += 1
            if n:
                del held[:n]
            if self.hold_paused and self.held_bytes <= HOLD_LIMIT // 2:
                self.hold_paused = False
                if self.paused_since is None:
                    self._resume_reading()
        if self.half_closed:
            self._close_when_done()

    def _write_own(self, data: bytes, ts: float) -> None:
        transport = self.transport
        assert transport is not None
        transport.write(data)
        engine = self.engine
        engine.stats.bytes_to_clients += len(data)
        engine.observer.chunk(self._own_stream(ts), _S2C, data, ts)

    def _close_when_done(self) -> None:
        """A half-closed client whose requests are all answered, and written: closed."""
        if self.outstanding or self.midway or self.held or self.waiting or self.closed:
            return
        transport = self.transport
        self.closed = True
        self.drop_reason = None
        if transport is not None:
            transport.close()
        self._finish_half_closed()

    def _forget_held(self) -> None:
        """The client is gone: what waited for it is never written."""
        self.held.clear()
        self.waiting.clear()
        self.held_bytes = 0
        self.midway = False

    def _own_stream(self, ts: float) -> Stream:
        """The stream of the proxy's own answers to this client (made at its CONNECT,
        :meth:`connection_made`; ``ts`` is unused there)."""
        own = self.own
        if own is None:  # a client that never connected through a socket
            engine = self.engine
            own = self.own = engine.observer.new_stream(Transport.TCP, self.peer, engine.name)
        return own

    def _finish_half_closed(self) -> None:
        engine = self.engine
        engine.clients.discard(self)
        link = self.link
        if link is not None and link.owner is self:
            link.close()
        info = {"how": "fin", "by": "client"}
        engine.observer.event(self.stream, EventKind.DISCONNECT, info)

    def notice(self, message: str, info: dict[str, Any]) -> None:
        self.engine.observer.event(self.stream, EventKind.NOTICE, {"message": message, **info})

    def unanswered(self, entry: Pending, code: int) -> None:
        """A silent client's request the gateway cannot answer (``code`` 0x0A/0x0B)."""

    def drop(self, reason: str, count: bool = True) -> None:
        """Disconnect this client (reset), with ``reason`` in the log."""
        if self.closed:
            return
        if count:
            self.engine.stats.clients_dropped += 1
        self.drop_reason = reason
        self.closed = True
        self._forget_held()
        self.notice(f"client {self.peer} dropped: {reason}", {"client": self.peer})
        if self.transport is not None:
            self.transport.abort()
