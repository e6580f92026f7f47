"""TCP reassembly for passive captures: one :class:`TcpConnection` per connection.

A connection turns the segments a capture saw into in-order payload
:class:`~mbmon.model.Chunk` s per direction, plus CONNECT, GAP and DISCONNECT
:class:`~mbmon.model.Event` s. The rules, per direction:

* **Start.** The SYN (or SYN-ACK) fixes the first sequence number. Without one
  (capture started mid-connection) the first segment that carries payload or a
  FIN does; bytes before it are never reported.
* **In order.** A segment at the expected sequence number is delivered at once,
  as one chunk with the packet's timestamp. Sequence numbers are compared
  modulo 2^32 (wraparound is invisible).
* **Retransmission / overlap.** Bytes already delivered are dropped; a segment
  that overlaps old and new bytes delivers only the new ones.
* **Out of order.** A segment ahead of the expected number is held (at most
  ``limit`` bytes per direction) and delivered as soon as the hole fills, as
  chunks of its own that keep the segment's own capture time: every chunk
  carries the time of the packet that carried its bytes, so an ADU held behind
  a hole keeps the time it was sent (its last byte's segment), not the time
  the hole was filled or given up.
* **Gaps.** A hole is given up, reported as ``Event(GAP, info={"direction",
  "bytes", "reason"})`` and skipped, when (a) the other side acknowledges bytes
  beyond it (``reason="acked-unseen"``: the receiver has them, so no
  retransmission will ever show them to us; an ack more than 16 MiB ahead is
  ignored as garbage), (b) the held bytes exceed ``limit``
  (``"buffer-limit"``), (c) the connection is reset or replaced (``"reset"``,
  ``"replaced"``), (d) the capture ends (``"end-of-capture"``), (e) the oldest
  held segment has waited ``timeout`` seconds of capture time
  (:meth:`TcpConnection.expire_holes`, ``"timeout"``; the GAP is stamped with
  that deadline), or (f) the connection expires idle (``"idle"``). Held bytes
  after the hole are then delivered; the decoder resynchronises. A segment's
  acknowledgement is applied before its own payload: the bytes a hole was
  holding back were received before the reply was sent, so they come first.
* **CONNECT** once per connection, at the first SYN or SYN-ACK seen (a capture
  that starts mid-connection has none).
* **DISCONNECT** once per connection: at a RST (``how="rst"``, ``by`` = its
  sender), or when both directions' FINs have been reached in sequence order
  (``how="fin"``, ``by`` = the side that sent the first FIN), so every byte sent
  before the FINs (including the answer to a half-closed request) comes first.
  A connection that saw only one FIN when the capture ends gets its DISCONNECT
  from :meth:`TcpConnection.finish` with ``half_closed=True``.
* **Idle.** :meth:`TcpConnection.expire` ends a connection that saw no packet
  for a while (the dissector's idle timeout): held bytes are released first,
  then ``DISCONNECT`` with ``how="idle"``.
* **After the end.** Payload on a closed connection is counted and dropped; a
  new SYN on the same addresses is a new connection, and so is a SYN-ACK or
  payload far from the old sequence numbers after the end (the caller's job:
  see :meth:`TcpConnection.is_new`).

Pure: no I/O, no clocks; the caller feeds parsed segments. A ``watcher`` (the
dissector) is told when a connection starts holding bytes behind a hole and
when it closes, so it can schedule hole timeouts and release closed
connections without looking at every connection on every packet.
"""

from __future__ import annotations

from bisect import insort
from typing import Protocol

from mbmon.model import Chunk, Direction, Event, EventKind, Stream, fast_constructor

FIN = 0x01
SYN = 0x02
RST = 0x04
ACK = 0x10

_MASK = 0xFFFFFFFF
_HALF = 0x80000000
# An acknowledgement further ahead than this is taken for garbage (fuzzed or
# corrupt headers), not for evidence of lost bytes: it is ignored.
MAX_ACK_JUMP = 1 << 24
# Payload after a connection ended this far from its sequence numbers is taken
# for a new connection on the same addresses whose handshake was not captured.
REUSE_DISTANCE = 1 << 20


#: ``Chunk(ts, stream, direction, data)`` made about twice as fast (one per segment)
make_chunk = fast_constructor(Chunk)
_C2S = Direction.C2S
_S2C = Direction.S2C


class Watcher(Protocol):
    """Who is told about a connection's life (the dissector)."""

    def held(self, conn: TcpConnection, ts: float) -> None:
        """``conn`` started holding bytes behind a hole at ``ts`` (none held before)."""

    def closed(self, conn: TcpConnection, ts: float) -> None:
        """``conn`` ended (both FINs reached, a RST, or a half-closed end)."""


class TcpStats:
    """Counters shared by every connection of one capture."""

    __slots__ = (
        "after_close",
        "gap_bytes",
        "gaps",
        "out_of_order",
        "overlaps",
        "retransmissions",
    )

    def __init__(self) -> None:
        self.retransmissions = 0  # segments whose payload was entirely old
        self.overlaps = 0  # segments that carried old and new bytes
        self.out_of_order = 0  # segments held because a hole preceded them
        self.gaps = 0
        self.gap_bytes = 0
        self.after_close = 0  # payload segments seen after the connection ended

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.__slots__}


class _Half:
    """One direction's reassembly state."""

    __slots__ = ("direction", "done", "fin", "held", "held_bytes", "isn", "nxt")

    def __init__(self, direction: Direction) -> None:
        self.direction = direction
        self.nxt: int | None = None  # next expected sequence number (32-bit)
        self.isn: int | None = None  # from the SYN, when seen
        # (seq, data, capture time), in sequence order
        self.held: list[tuple[int, bytes, float]] = []
        self.held_bytes = 0
        self.fin: int | None = None  # sequence number of the FIN
        self.done = False  # FIN reached in order


def _signed(diff: int) -> int:
    diff &= _MASK
    return diff - 0x100000000 if diff & _HALF else diff


class TcpConnection:
    """Reassembly of one TCP connection (both directions) on a known :class:`Stream`.

    Feed every segment of the connection to :meth:`segment`; call :meth:`finish`
    when the capture ends. Output goes to the ``out`` list passed in (no list is
    made per segment).
    """

    __slots__ = (
        "_c2s",
        "_s2c",
        "closed",
        "connected",
        "fin_by",
        "last",
        "limit",
        "stats",
        "stream",
        "watcher",
    )

    def __init__(
        self,
        stream: Stream,
        *,
        limit: int = 1 << 20,
        stats: TcpStats | None = None,
        watcher: Watcher | None = None,
    ) -> None:
        self.stream = stream
        self.limit = limit
        self.stats = stats if stats is not None else TcpStats()
        self.watcher = watcher
        self._c2s = _Half(_C2S)
        self._s2c = _Half(_S2C)
        self.connected = False
        self.closed = False
        self.fin_by: str | None = None
        self.last = float("-inf")  # capture time of the last segment (idle expiry)

    def _closed(self, ts: float) -> None:
        self.closed = True
        if self.watcher is not None:
            self.watcher.closed(self, ts)

    def is_new(self, from_client: bool, seq: int, flags: int, has_payload: bool) -> bool:
        """Whether this segment belongs to a new connection on the same addresses:

        * a SYN (without ACK) after this connection ended, or with another initial
          sequence number, or on a connection that was picked up without its SYN;
        * a SYN-ACK after the end or with another initial sequence number (the new
          connection's SYN was not captured);
        * payload after the end more than :data:`REUSE_DISTANCE` away from where
          this direction stopped (the new connection's handshake was not captured;
          a straggler of the old one lies close to it).
        """
        half = self._c2s if from_client else self._s2c
        syn_ack = flags & (SYN | ACK)
        if syn_ack == SYN:
            if self.closed:
                return True
            if half.isn is None:
                # The SYN's sender must be the client; a connection that saw no SYN
                # from it so far, but already traffic, is a different connection.
                other = self._s2c if from_client else self._c2s
                return half.nxt is not None or other.nxt is not None
            return seq != half.isn
        if syn_ack == SYN | ACK:
            return self.closed or (half.isn is not None and seq != half.isn)
        if self.closed and has_payload:
            return half.nxt is None or abs(_signed(seq - half.nxt)) > REUSE_DISTANCE
        return False

    def segment(
        self,
        ts: float,
        from_client: bool,
        seq: int,
        ack: int,
        flags: int,
        payload: bytes,
        out: list[Chunk | Event],
    ) -> None:
        """Account for one captured segment; append what it releases to ``out``."""
        self.last = ts
        if from_client:
            half, other = self._c2s, self._s2c
        else:
            half, other = self._s2c, self._c2s
        if not flags & 0x07 and half.nxt == seq and not half.held and half.fin is None:
            # fast path: in-order data or a pure ACK on an open connection
            if self.closed:
                if payload:
                    self.stats.after_close += 1
                return
            if flags & ACK:
                nxt = other.nxt
                if nxt is not None and nxt != ack and not other.done:
                    diff = (ack - nxt) & _MASK
                    if 0 < diff <= MAX_ACK_JUMP:
                        self._acked(other, ts, ack, out)
            if payload:
                out.append(make_chunk(ts, self.stream, half.direction, payload))
                half.nxt = (seq + len(payload)) & _MASK
            return
        self.segment_general(ts, from_client, seq, ack, flags, payload, out)

    def segment_general(
        self,
        ts: float,
        from_client: bool,
        seq: int,
        ack: int,
        flags: int,
        payload: bytes,
        out: list[Chunk | Event],
    ) -> None:
        """:meth:`segment` without its fast branch: every segment the general way.

        :meth:`segment` takes the common case (in-order data or a pure ACK on an
        open connection) in a few lines and hands everything else here; the
        differential tests feed the same segments both ways and pin the results
        equal."""
        self.last = ts
        if from_client:
            half, other = self._c2s, self._s2c
        else:
            half, other = self._s2c, self._c2s
        if self.closed:
            if payload:
                self.stats.after_close += 1
            return
        if flags & RST:
            self._flush(half, ts, out, "reset")
            self._flush(other, ts, out, "reset")
            out.append(
                Event(
                    ts,
                    self.stream,
                    EventKind.DISCONNECT,
                    {"how": "rst", "by": "client" if from_client else "server"},
                )
            )
            self._closed(ts)
            return
        if flags & SYN and flags & FIN:
            # SYN+FIN is no valid segment (stacks drop it; fuzzers send it): the FIN
            # must not end a direction whose real bytes are still to come.
            flags &= ~FIN
        if flags & SYN:
            if half.isn is None and half.nxt is None:
                half.isn = seq
                half.nxt = (seq + 1) & _MASK
            if not self.connected:
                self.connected = True
                out.append(Event(ts, self.stream, EventKind.CONNECT))
            seq = (seq + 1) & _MASK
        elif half.nxt is None and (payload or flags & FIN):
            half.nxt = seq
        # The acknowledgement first: what the sender had received (and what a hole
        # it reveals releases) came before what it sends in reply.
        if flags & ACK and other.nxt is not None and not other.done:
            diff = (ack - other.nxt) & _MASK
            if 0 < diff <= MAX_ACK_JUMP:
                self._acked(other, ts, ack, out)
        if payload and half.nxt is not None:
            if half.done:
                self.stats.after_close += 1
            else:
                self._data(half, ts, seq, payload, out)
        if flags & FIN and half.fin is None and half.nxt is not None:
            half.fin = (seq + len(payload)) & _MASK
            if self.fin_by is None:
                self.fin_by = "client" if from_client else "server"
            self._drain(half, ts, out)

    def finish(self, ts: float, out: list[Chunk | Event], reason: str = "end-of-capture") -> None:
        """The capture ended (or the addresses were reused): give up every hole,
        deliver what was held, and close a half-closed connection."""
        if self.closed:
            return
        self._flush(self._c2s, ts, out, reason)
        self._flush(self._s2c, ts, out, reason)
        if not self.closed and self.fin_by is not None and reason == "end-of-capture":
            out.append(
                Event(
                    ts,
                    self.stream,
                    EventKind.DISCONNECT,
                    {"how": "fin", "by": self.fin_by, "half_closed": True},
                )
            )
            self._closed(ts)

    def seen(self) -> bool:
        """Whether the connection showed anything (a SYN, payload or a FIN)."""
        return self.connected or self._c2s.nxt is not None or self._s2c.nxt is not None

    def expire(self, ts: float, out: list[Chunk | Event], reason: str) -> None:
        """The connection went idle (no packet for the idle timeout; ``ts`` is when
        it expired): give up every hole and deliver what was held, then one
        ``DISCONNECT`` with ``how="idle"`` and ``reason`` (unless it showed nothing
        at all: a lone ACK). Its state can then be dropped."""
        if self.closed:
            return
        self._flush(self._c2s, ts, out, "idle")
        self._flush(self._s2c, ts, out, "idle")
        if not self.closed:
            if self.seen():
                info: dict[str, object] = {"how": "idle", "reason": reason}
                if self.fin_by is not None:
                    info["by"] = self.fin_by
                    info["half_closed"] = True
                out.append(Event(ts, self.stream, EventKind.DISCONNECT, info))
            self._closed(ts)

    def hole_deadline(self, timeout: float) -> float | None:
        """When the oldest held segment will have waited ``timeout``, or ``None``."""
        oldest = [t for half in (self._c2s, self._s2c) for _, _, t in half.held]
        return min(oldest) + timeout if oldest else None

    def expire_holes(self, now: float, timeout: float, out: list[Chunk | Event]) -> float | None:
        """Give up the holes in front of every segment held ``timeout`` seconds or
        longer at ``now`` (GAP ``reason="timeout"``, stamped with the moment the
        segment's wait ran out); return the next such moment, or ``None``."""
        for half in (self._c2s, self._s2c):
            while half.held and half.nxt is not None and not self.closed:
                due = min(t for _, _, t in half.held) + timeout
                if due > now:
                    break
                self._skip(half, due, half.held[0][0], out, "timeout")
        if self.closed:
            return None
        return self.hole_deadline(timeout)

    # -- internals ---------------------------------------------------------------

    def _data(
        self, half: _Half, ts: float, seq: int, payload: bytes, out: list[Chunk | Event]
    ) -> None:
        nxt = half.nxt
        assert nxt is not None
        diff = (seq - nxt) & _MASK
        if diff == 0:
            out.append(make_chunk(ts, self.stream, half.direction, payload))
            half.nxt = (nxt + len(payload)) & _MASK
            if half.held or half.fin is not None:
                self._drain(half, ts, out)
            return
        if diff & _HALF:  # starts before nxt: retransmission or overlap
            old = 0x100000000 - diff
            if old >= len(payload):
                self.stats.retransmissions += 1
                return
            self.stats.overlaps += 1
            payload = payload[old:]
            out.append(make_chunk(ts, self.stream, half.direction, payload))
            half.nxt = (nxt + len(payload)) & _MASK
            if half.held or half.fin is not None:
                self._drain(half, ts, out)
            return
        self.stats.out_of_order += 1
        if not half.held and self.watcher is not None:
            other = self._s2c if half is self._c2s else self._c2s
            if not other.held:
                self.watcher.held(self, ts)
        insort(half.held, (seq, payload, ts), key=lambda item: _signed(item[0] - nxt))
        half.held_bytes += len(payload)
        while half.held and half.held_bytes > self.limit:
            self._skip(half, ts, half.held[0][0], out, "buffer-limit")

    def _drain(self, half: _Half, ts: float, out: list[Chunk | Event]) -> None:
        """Deliver held segments that became contiguous, each with its own capture
        time; notice a FIN reached."""
        held = half.held
        nxt = half.nxt
        assert nxt is not None
        while held:
            seq, data, at = held[0]
            diff = _signed(seq - nxt)
            if diff > 0:
                break
            held.pop(0)
            half.held_bytes -= len(data)
            if -diff >= len(data):
                continue
            if diff:
                data = data[-diff:]
            out.append(make_chunk(at, self.stream, half.direction, data))
            nxt = (nxt + len(data)) & _MASK
        half.nxt = nxt
        if half.fin is not None and not half.done and _signed(nxt - half.fin) >= 0:
            half.done = True
            half.nxt = (half.fin + 1) & _MASK
            half.held.clear()
            half.held_bytes = 0
            other = self._s2c if half is self._c2s else self._c2s
            if other.done and not self.closed:
                out.append(
                    Event(ts, self.stream, EventKind.DISCONNECT, {"how": "fin", "by": self.fin_by})
                )
                self._closed(ts)

    def _skip(self, half: _Half, ts: float, to: int, out: list[Chunk | Event], reason: str) -> None:
        """Give up the hole from ``half.nxt`` to ``to`` (a GAP), then drain."""
        assert half.nxt is not None
        missing = _signed(to - half.nxt)
        if missing > 0:
            self.stats.gaps += 1
            self.stats.gap_bytes += missing
            out.append(
                Event(
                    ts,
                    self.stream,
                    EventKind.GAP,
                    {"direction": half.direction.value, "bytes": missing, "reason": reason},
                )
            )
            half.nxt = to & _MASK
        self._drain(half, ts, out)

    def _acked(self, half: _Half, ts: float, ack: int, out: list[Chunk | Event]) -> None:
        """The peer acknowledged up to ``ack``, beyond what this direction delivered:
        the bytes in between were lost by the capture, not by the network."""
        while not half.done:
            nxt = half.nxt
            assert nxt is not None
            ahead = _signed(ack - nxt)
            if ahead <= 0:
                return
            to = ack
            if half.held:
                first = _signed(half.held[0][0] - nxt)
                if first < ahead:
                    to = half.held[0][0]
            if half.fin is not None:
                fin_at = _signed(half.fin - nxt)
                if 0 <= fin_at < _signed(to - nxt):
                    to = half.fin
            if to == nxt:  # a FIN right here: the drain below reaches it
                self._drain(half, ts, out)
                if half.nxt == nxt:
                    return
                continue
            self._skip(half, ts, to, out, "acked-unseen")

    def _flush(self, half: _Half, ts: float, out: list[Chunk | Event], reason: str) -> None:
        """Give up every hole of this direction (the connection is over)."""
        while half.held and half.nxt is not None:
            self._skip(half, ts, half.held[0][0], out, reason)
        if half.fin is not None and not half.done and half.nxt is not None:
            self._skip(half, ts, half.fin, out, reason)
