"""The dissector's flow table: every TCP connection, UDP pair and RTU bus it
knows, the streams they are, and how long their state lives.

:class:`FlowTable` is the base of :class:`mbmon.sources.dissect.Dissector`: the
dissector parses packets and counts them; this module owns what a parsed
packet's addresses become (a new or known flow, a stream with its client and
server) and the lifetime of every piece of per-flow state. State is bounded, so
a run can last weeks:

* a TCP connection that ends (both FINs, or a RST) leaves its reassembly state
  at once; its addresses stay known for :data:`CLOSED_LINGER` seconds (at most
  :data:`MAX_CLOSED` of them) so that its stragglers (last ACKs, retransmitted
  FINs) are not taken for a new connection, like TCP's TIME-WAIT;
* a connection, UDP pair or bus with no packet for ``idle_timeout`` seconds of
  capture time expires: held bytes are released first, then
  ``Event(DISCONNECT, info={"how": "idle", "reason": ...})`` stamped with the
  moment it expired;
* more than ``max_flows`` open TCP connections (or UDP pairs) expire the least
  recently active eighth of them the same way (``reason`` says so), whatever
  the idle timeout: a flood of half-open connections cannot grow the state;
* a TCP hole (a lost or late segment) is given up ``hole_timeout`` seconds
  after the oldest segment held behind it arrived (``GAP``, ``reason="timeout"``),
  not only when an ACK passes it or the capture ends (``None``: never).

Time is the packets' own: the dissector handles what fell due by a packet's
timestamp before the packet; :meth:`FlowTable.tick` moves time on while no
packet arrives (a live source's clock); :meth:`FlowTable.next_deadline` says
when that is next needed.
"""

from __future__ import annotations

import ipaddress
from collections import OrderedDict
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.sources.tcpflow import ACK, SYN, TcpConnection, TcpStats

if TYPE_CHECKING:
    from mbmon.analysis.detect import PortDetector

__all__ = ["CLOSED_LINGER", "MAX_CLOSED", "MAX_FLOWS", "FlowTable", "Key", "address_text"]

_TCP_HOLD_LIMIT = 1 << 20  # out-of-order bytes held per TCP direction
#: Seconds (capture time) the addresses of a closed TCP connection stay known.
CLOSED_LINGER = 60.0
#: Closed connections remembered at most (the oldest are forgotten first).
MAX_CLOSED = 4096
#: Open TCP connections (and, apart, UDP pairs) at most before the least recently
#: active are expired.
MAX_FLOWS = 10_000
_MAX_BUSES = 1024  # RTU buses (interfaces of link type 147) at most
_NEVER = float("inf")

_C2S = Direction.C2S
_S2C = Direction.S2C

#: A flow's key: (source + destination address, source port, destination port).
Key = tuple[bytes, int, int]


def address_text(raw: bytes, port: int) -> str:
    """An endpoint as text: ``a.b.c.d:port`` for a 4-byte address, ``[v6]:port``
    for a 16-byte one."""
    if len(raw) == 4:
        return f"{raw[0]}.{raw[1]}.{raw[2]}.{raw[3]}:{port}"
    return f"[{ipaddress.IPv6Address(raw).compressed}]:{port}"


class FlowTable:
    """The flows a dissector knows and their lifetime (see the module docstring):
    TCP connections by both directions' keys, UDP pairs, RTU buses; stream
    identity; hole, idle and linger timeouts; eviction past ``max_flows``.

    ``ports``: the configured Modbus ports; ``rtu_ports``: those that carry RTU;
    ``detector``: port detection, or ``None``. The other arguments are the
    :class:`~mbmon.sources.dissect.Dissector`'s.
    """

    def __init__(
        self,
        ports: frozenset[int],
        rtu_ports: frozenset[int],
        detector: PortDetector | None,
        bus_name: str,
        *,
        new_stream: Callable[[Transport, str, str], Stream] | None,
        idle_timeout: float | None,
        hole_timeout: float | None,
        max_flows: int,
    ) -> None:
        self.rtu_ports = rtu_ports
        self.ports = ports
        #: port detection (``config.detect``): the detector, else ``None``
        self.detector = detector
        self.bus_name = bus_name
        self.new_stream = new_stream
        self.idle_timeout = _NEVER if idle_timeout is None else float(idle_timeout)
        self.hole_timeout = hole_timeout
        self.max_flows = max(8, max_flows)
        # both directions' keys -> (connection, whether that key's sender is the client)
        self.tcp: dict[Key, tuple[TcpConnection, bool]] = {}
        self.udp: dict[Key, tuple[Stream, Direction]] = {}
        self.buses: dict[int, Stream] = {}
        # open connections -> one of their keys, in order of creation
        self.connections: dict[TcpConnection, Key] = {}
        # closed connections -> (one of their keys, when they are forgotten), in closing
        # order (an OrderedDict: a dict emptied from the front makes next(iter()) slow)
        self._closed: OrderedDict[TcpConnection, tuple[Key, float]] = OrderedDict()
        # connections holding bytes behind a hole -> when the oldest waited hole_timeout
        self._holes: dict[TcpConnection, float] = {}
        self._udp_keys: dict[int, tuple[Key, Stream]] = {}  # stream id -> (key, stream)
        self._udp_last: dict[int, float] = {}  # stream id -> last datagram's time
        self._bus_last: dict[int, float] = {}  # interface -> last record's time
        self._bus_names: dict[int, str] = {}  # interface -> stream name (kept: small)
        self._idle_due = _NEVER  # next idle scan
        self._due = _NEVER  # min(idle scan, oldest hole, closed connection to forget)
        self.next_id = 0  # streams made
        self.tcp_stats = TcpStats()
        self.expired = 0  # flows ended idle (timeout, or too many open: max_flows)
        self.hole_timeouts = 0  # holes given up by the hole timeout

    def tick(self, now: float) -> list[Chunk | Event]:
        """Time moved on to ``now`` without packets: give up holes, expire idle
        flows and forget closed connections that fell due; what that releases."""
        out: list[Any] = []
        if now >= self._due:
            self._tick(now, out)
        return out

    def next_deadline(self) -> float | None:
        """When :meth:`tick` next has something to do, or ``None``."""
        return None if self._due == _NEVER else self._due

    def finish(self, ts: float) -> list[Chunk | Event]:
        """The input ended at ``ts``: release every held TCP byte and close
        half-closed connections (GAP ``end-of-capture``, DISCONNECT ``half_closed``)."""
        out: list[Any] = []
        for conn in list(self.connections):
            conn.finish(ts, out)
        return out

    # ------------------------------------------------------------------ time

    def _tick(self, now: float, out: list[Any]) -> None:
        """Everything due by ``now``, in a fixed order: holes, idle flows, closed
        connections to forget. Recomputes ``_due``."""
        timeout = self.hole_timeout
        if timeout is not None:
            self._expire_holes(now, timeout, out)
        if now >= self._idle_due:
            self._expire_idle(now, out)
        self._forget_closed(now)
        self._set_due()

    def _set_due(self) -> None:
        due = self._idle_due
        if self._holes:
            due = min(due, min(self._holes.values()))
        if self._closed:
            due = min(due, next(iter(self._closed.values()))[1])
        self._due = due

    def _expire_holes(self, now: float, timeout: float, out: list[Any]) -> None:
        holes = self._holes
        for conn, due in list(holes.items()):
            if due > now or conn not in holes:
                continue
            gaps = conn.stats.gaps
            again = conn.expire_holes(now, timeout, out)
            self.hole_timeouts += conn.stats.gaps - gaps
            if again is None:
                holes.pop(conn, None)
            else:
                holes[conn] = again

    def _expire_idle(self, now: float, out: list[Any]) -> None:
        """Expire every flow idle for ``idle_timeout`` at ``now``; schedule the
        next scan at the earliest survivor's expiry, but not sooner than a second
        (or an eighth of the timeout) from now: a scan looks at every flow."""
        idle = self.idle_timeout
        limit = now - idle
        reason = f"no packets for {idle:g} s"
        first = _NEVER
        for conn in list(self.connections):
            last = conn.last
            if last <= limit:
                self.expired += 1
                conn.expire(last + idle, out, reason)
                self._forget(conn)
            elif last < first:
                first = last
        for sid, last in list(self._udp_last.items()):
            if last <= limit:
                self._end_udp(sid, last + idle, reason, out)
            elif last < first:
                first = last
        for iface, last in list(self._bus_last.items()):
            if last <= limit:
                self.expired += 1
                self._end_bus(iface, last + idle, "idle", reason, out)
            elif last < first:
                first = last
        floor = now + min(idle / 8, 1.0)
        self._idle_due = _NEVER if first == _NEVER else max(first + idle, floor)

    def _forget_closed(self, now: float) -> None:
        closed = self._closed
        while closed:
            conn, (key, until) = next(iter(closed.items()))
            if until > now:
                break
            closed.popitem(last=False)
            self._drop_tcp(conn, key)

    # ------------------------------------------------------------------ flow state

    def held(self, conn: TcpConnection, ts: float) -> None:
        """Watcher hook: ``conn`` holds bytes behind a hole since ``ts``."""
        if self.hole_timeout is None:
            return
        due = ts + self.hole_timeout
        if conn not in self._holes:
            self._holes[conn] = due
            if due < self._due:
                self._due = due

    def closed(self, conn: TcpConnection, ts: float) -> None:
        """Watcher hook: ``conn`` ended; its state goes, its addresses linger."""
        key = self.connections.pop(conn, None)
        self._holes.pop(conn, None)
        if key is None:  # expired or replaced: already forgotten
            return
        closed = self._closed
        until = ts + CLOSED_LINGER
        if not closed and until < self._due:
            self._due = until
        closed[conn] = (key, until)
        if len(closed) > MAX_CLOSED:
            old, (old_key, _) = closed.popitem(last=False)
            self._drop_tcp(old, old_key)

    def _forget(self, conn: TcpConnection) -> None:
        """Drop an open connection at once (expired, or replaced by a new one)."""
        key = self.connections.pop(conn, None)
        self._holes.pop(conn, None)
        lingering = self._closed.pop(conn, None)
        if key is None and lingering is not None:
            key = lingering[0]
        if key is not None:
            self._drop_tcp(conn, key)

    def _drop_tcp(self, conn: TcpConnection, key: Key) -> None:
        """Remove ``conn``'s two keys, unless a newer connection took them over."""
        addrs, sport, dport = key
        half = len(addrs) // 2
        for k in (key, (addrs[half:] + addrs[:half], dport, sport)):
            flow = self.tcp.get(k)
            if flow is not None and flow[0] is conn:
                del self.tcp[k]

    def _end_udp(self, sid: int, ts: float, reason: str, out: list[Any]) -> None:
        """Forget a UDP pair (DISCONNECT ``how="idle"`` at ``ts``)."""
        self.expired += 1
        key, stream = self._udp_keys.pop(sid)
        del self._udp_last[sid]
        addrs, sport, dport = key
        half = len(addrs) // 2
        self.udp.pop(key, None)
        self.udp.pop((addrs[half:] + addrs[:half], dport, sport), None)
        out.append(Event(ts, stream, EventKind.DISCONNECT, {"how": "idle", "reason": reason}))

    def _stream(self, transport: Transport, client: str, server: str) -> Stream:
        if self.new_stream is not None:
            stream = self.new_stream(transport, client, server)
        else:
            stream = Stream(self.next_id, transport, client, server)
        self.next_id += 1
        return stream

    def _roles(self, key: tuple[bytes, int, int], flags: int) -> tuple[bool, int]:
        """Whether the sender of this first packet is the client, and the server port.

        The server is the endpoint whose port is configured; when both are, the SYN
        receiver (SYN-ACK sender) is, else the lower port, else the receiver."""
        _, sport, dport = key
        src_in, dst_in = sport in self.ports, dport in self.ports
        if src_in and dst_in:
            if flags & (SYN | ACK) == SYN:
                sender_is_client = True
            elif flags & (SYN | ACK) == SYN | ACK:
                sender_is_client = False
            else:
                sender_is_client = dport <= sport
        else:
            sender_is_client = dst_in
        server_port = dport if sender_is_client else sport
        return sender_is_client, server_port

    def _endpoints(self, key: tuple[bytes, int, int], sender_is_client: bool) -> tuple[str, str]:
        addrs, sport, dport = key
        half = len(addrs) // 2
        src, dst = address_text(addrs[:half], sport), address_text(addrs[half:], dport)
        return (src, dst) if sender_is_client else (dst, src)

    def _tcp_flow(
        self,
        key: tuple[bytes, int, int],
        flow: tuple[TcpConnection, bool] | None,
        ts: float,
        seq: int,
        flags: int,
        has_payload: bool,
        out: list[Any],
    ) -> tuple[TcpConnection, bool]:
        """The connection a segment belongs to: a new one for new addresses, or when
        the segment opens a new connection on addresses seen before."""
        if flow is None:
            if len(self.connections) >= self.max_flows:
                self._evict_tcp(ts, out)
            return self._new_tcp(key, flags, ts)
        old = flow[0]
        if (flags & SYN or old.closed) and old.is_new(flow[1], seq, flags, has_payload):
            old.finish(ts, out, "replaced")
            self._forget(old)
            return self._new_tcp(key, flags, ts)
        return flow

    def _evict_tcp(self, ts: float, out: list[Any]) -> None:
        """Too many open connections: the least recently active eighth expire."""
        conns = self.connections
        oldest = sorted(conns, key=lambda conn: conn.last)[: len(conns) // 8]
        reason = f"more than {self.max_flows} open connections"
        for conn in oldest:
            self.expired += 1
            conn.expire(ts, out, reason)
            self._forget(conn)

    def _evict_udp(self, ts: float, out: list[Any]) -> None:
        """Too many UDP pairs: the least recently active eighth expire."""
        last = self._udp_last
        oldest = sorted(last, key=last.__getitem__)[: len(last) // 8]
        reason = f"more than {self.max_flows} UDP pairs"
        for sid in oldest:
            self._end_udp(sid, ts, reason, out)

    def _new_tcp(
        self, key: tuple[bytes, int, int], flags: int, ts: float
    ) -> tuple[TcpConnection, bool]:
        detected = None
        if self.detector is not None and key[1] not in self.ports and key[2] not in self.ports:
            detected = self.detector.role(key)
        if detected is None:
            sender_is_client, server_port = self._roles(key, flags)
            transport = Transport.RTU_OVER_TCP if server_port in self.rtu_ports else Transport.TCP
        else:
            sender_is_client, transport = detected
        client, server = self._endpoints(key, sender_is_client)
        conn = TcpConnection(
            self._stream(transport, client, server),
            limit=_TCP_HOLD_LIMIT,
            stats=self.tcp_stats,
            watcher=self,
        )
        conn.last = ts
        self.connections[conn] = key
        if self._idle_due == _NEVER:
            self._idle_due = ts + self.idle_timeout
            self._due = min(self._due, self._idle_due)
        addrs, sport, dport = key
        half = len(addrs) // 2
        flow = (conn, sender_is_client)
        self.tcp[key] = flow
        self.tcp[(addrs[half:] + addrs[:half], dport, sport)] = (conn, not sender_is_client)
        return flow

    def _new_udp(self, key: tuple[bytes, int, int], ts: float) -> tuple[Stream, Direction]:
        sender_is_client, server_port = self._roles(key, 0)
        transport = Transport.RTU_OVER_UDP if server_port in self.rtu_ports else Transport.UDP
        client, server = self._endpoints(key, sender_is_client)
        stream = self._stream(transport, client, server)
        addrs, sport, dport = key
        half = len(addrs) // 2
        flow = (stream, _C2S if sender_is_client else _S2C)
        self.udp[key] = flow
        self._udp_keys[stream.id] = (key, stream)
        if self._idle_due == _NEVER:
            self._idle_due = ts + self.idle_timeout
            self._due = min(self._due, self._idle_due)
        self.udp[(addrs[half:] + addrs[:half], dport, sport)] = (
            stream,
            _S2C if sender_is_client else _C2S,
        )
        return flow

    def _new_bus(self, iface: int, ts: float, out: list[Any]) -> Stream:
        if len(self.buses) >= _MAX_BUSES:  # the least recently heard bus goes
            old = min(self._bus_last, key=self._bus_last.__getitem__)
            self._end_bus(old, ts, "evicted", f"more than {_MAX_BUSES} buses", out)
        name = self._bus_names.get(iface)
        if name is None:
            name = self.bus_name if not self._bus_names else f"{self.bus_name}#{iface}"
            if len(self._bus_names) < 4 * _MAX_BUSES:
                self._bus_names[iface] = name
        if self._idle_due == _NEVER:
            self._idle_due = ts + self.idle_timeout
            self._due = min(self._due, self._idle_due)
        stream = self.buses[iface] = self._stream(Transport.RTU, name, name)
        return stream

    def _end_bus(self, iface: int, ts: float, how: str, reason: str, out: list[Any]) -> None:
        stream = self.buses.pop(iface)
        del self._bus_last[iface]
        out.append(Event(ts, stream, EventKind.DISCONNECT, {"how": how, "reason": reason}))
