"""Packets in, Modbus byte streams out: the dissector every packet source shares.

This module owns what happens to one captured packet, whatever read it (a
capture file, :mod:`mbmon.sources.pcapfile`; a live raw socket, scapy as a byte
source): the link layer (Ethernet, VLAN tags, Linux cooked v1/v2, raw IP, BSD
loopback, USER0 = an RTU bus), IPv4/IPv6 (options, extension headers,
fragments counted), TCP/UDP, deciding which packets are Modbus (by port,
:class:`CaptureConfig`), naming streams, reassembly of TCP
(:mod:`mbmon.sources.tcpflow`) and the lifetime of every piece of per-flow
state. The output is :class:`~mbmon.model.Chunk` and
:class:`~mbmon.model.Event` items.

Bytes never raise: headers that make no sense are counted (:meth:`Dissector.stats`)
and skipped.

Streams: TCP and UDP packets to or from a configured port are Modbus; the
endpoint with the configured port is the server (both configured: the SYN
receiver, else the lower port). With ``CaptureConfig.detect``, a TCP
connection on any other port becomes a stream once its own bytes prove it
Modbus (:mod:`mbmon.analysis.detect`: MBAP or RTU structure and an answered
request); its held segments are then replayed through reassembly, the
requester is the client, and later connections to that server endpoint are
streams from their first packet (:meth:`Dissector.detected` lists them).
Without ``new_stream`` stream ids count from 0 in order of first appearance;
with it (a hub's ``new_stream``), the caller allocates them, so several
sources of one run never collide. A TCP connection
reopened on the same addresses (a SYN after the end, or with a new initial
sequence number) is a new stream. UDP: one chunk per datagram. Link type 147
(USER0): each record is bytes of one RTU bus, stream ``client = server =
bus_name`` (``name#<interface>`` for a second bus).

State is bounded, so a run can last weeks:

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
  not only when an ACK passes it or the capture ends (``None``: never);
* the non-Modbus port counter (:meth:`Dissector.busiest_ports`) keeps at most
  :data:`MAX_PORTS` ports.

Time is the packets' own: :meth:`Dissector.packet` first handles what fell due
by the packet's timestamp; :meth:`Dissector.tick` moves time on while no packet
arrives (a live source's clock); :meth:`Dissector.next_deadline` says when that
is next needed. Chunks carry the capture time of the packet that carried their
bytes, also when they were held behind a hole.
"""

from __future__ import annotations

import heapq
import ipaddress
import struct
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.sources.headers import ipv4_header, ipv6_header, link_layer
from mbmon.sources.tcpflow import ACK, SYN, TcpConnection, TcpStats, make_chunk

if TYPE_CHECKING:
    from mbmon.analysis.detect import PortDetector, Promotion

__all__ = ["CLOSED_LINGER", "MAX_CLOSED", "MAX_FLOWS", "MAX_PORTS", "CaptureConfig", "Dissector"]

_TCP_HOLD_LIMIT = 1 << 20  # out-of-order bytes held per TCP direction
#: Seconds (capture time) the addresses of a closed TCP connection stay known.
CLOSED_LINGER = 60.0
#: Closed connections remembered at most (the oldest are forgotten first).
MAX_CLOSED = 4096
#: Open TCP connections (and, apart, UDP pairs) at most before the least recently
#: active are expired.
MAX_FLOWS = 10_000
#: Distinct non-Modbus ports counted at most (later new ports are not counted).
MAX_PORTS = 4096
_MAX_BUSES = 1024  # RTU buses (interfaces of link type 147) at most
_UDP_PORT = 0x10000  # port counter key bit: UDP (else TCP)
_NEVER = float("inf")

_C2S = Direction.C2S
_S2C = Direction.S2C

Key = tuple[bytes, int, int]  # (source + destination address, source port, destination port)


@dataclass(frozen=True, slots=True)
class CaptureConfig:
    """Which ports carry Modbus.

    ``tcp_ports``: Modbus/TCP (MBAP) server ports, for TCP and UDP.
    ``rtu_ports``: RTU-over-TCP/UDP server ports; a port in both sets is RTU
    (the explicit choice wins over the default 502).
    ``detect``: also find Modbus/TCP and RTU over TCP on any other TCP port by
    the structure of the bytes (:mod:`mbmon.analysis.detect`); the one switch
    of port detection (a compiled core that does not detect declines when it
    is on).
    """

    tcp_ports: frozenset[int] = frozenset({502})
    rtu_ports: frozenset[int] = frozenset()
    detect: bool = False


def _address(raw: bytes, port: int) -> str:
    if len(raw) == 4:
        return f"{raw[0]}.{raw[1]}.{raw[2]}.{raw[3]}:{port}"
    return f"[{ipaddress.IPv6Address(raw).compressed}]:{port}"


_tcp_unpack = struct.Struct("!HHIIH").unpack_from
_udp_unpack = struct.Struct("!HHH").unpack_from
# Ethernet type, IPv4 (version/IHL, length, flags/offset, protocol, addresses), TCP
_eth_ipv4_tcp = struct.Struct("!12xHBxHxxHxBxx8sHHIIH").unpack_from


class Dissector:
    """From link-layer packets to chunks and events; owns stream identity and the
    lifetime of every flow's state (see the module docstring).

    ``new_stream(transport, client, server)``, when given, allocates the
    :class:`~mbmon.model.Stream` objects (a hub's ``new_stream``). ``bus_name``
    names RTU bus streams. ``idle_timeout`` (seconds of capture time, ``None``:
    never) expires flows without packets; ``hole_timeout`` (``None``: never)
    gives up TCP holes; ``max_flows`` bounds open TCP connections and UDP pairs.
    """

    def __init__(
        self,
        config: CaptureConfig,
        bus_name: str = "bus",
        *,
        new_stream: Callable[[Transport, str, str], Stream] | None = None,
        idle_timeout: float | None = 300.0,
        hole_timeout: float | None = 2.0,
        max_flows: int = MAX_FLOWS,
    ) -> None:
        self.rtu_ports = config.rtu_ports
        self.ports = config.tcp_ports | config.rtu_ports
        #: port detection (``config.detect``): the detector, else ``None``
        self.detector: PortDetector | None = None
        if config.detect:
            from mbmon.analysis.detect import PortDetector

            self.detector = PortDetector()
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
        self._ports: dict[int, int] = {}  # non-Modbus port (| _UDP_PORT) -> packets
        self._idle_due = _NEVER  # next idle scan
        self._due = _NEVER  # min(idle scan, oldest hole, closed connection to forget)
        self.next_id = 0  # streams made
        # time of the last packet that parsed (up to TCP/UDP, or a bus record): the
        # last good time when a damaged file ends (garbled records have no time)
        self.good_ts: float | None = None
        self.tcp_stats = TcpStats()
        self.modbus_packets = 0
        self.non_modbus = 0
        self.non_ip = 0
        self.truncated = 0
        self.fragments = 0
        self.malformed = 0
        self.unsupported_link = 0
        self.bus_records = 0
        self.expired = 0  # flows ended idle (timeout, or too many open: max_flows)
        self.hole_timeouts = 0  # holes given up by the hole timeout
        self.other_ports_dropped = 0  # non-Modbus packets whose port was not counted

    # ------------------------------------------------------------------ API

    def packet_bytes(self, ts: float, linktype: int, data: bytes) -> list[Chunk | Event]:
        """Dissect one packet of link type ``linktype`` captured at ``ts`` (a live
        capture's form of :meth:`packet`): the chunks and events it causes."""
        out: list[Any] = []
        self.packet(ts, linktype, 0, data, 0, len(data), out)
        return out

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

    def stats(self) -> dict[str, int]:
        """Counters: packets by fate, streams made, TCP reassembly figures, flows
        expired and how many are open now."""
        counters = {
            "modbus_packets": self.modbus_packets,
            "non_modbus": self.non_modbus,
            "non_ip": self.non_ip,
            "truncated": self.truncated,
            "fragments": self.fragments,
            "malformed": self.malformed,
            "unsupported_link": self.unsupported_link,
            "bus_records": self.bus_records,
            "streams": self.next_id,
            "expired": self.expired,
            "hole_timeouts": self.hole_timeouts,
            "open_connections": len(self.connections),
        }
        counters.update(self.tcp_stats.as_dict())
        return counters

    def busiest_ports(self, n: int = 5) -> list[tuple[str, int, int]]:
        """The ``n`` non-Modbus ports with the most packets: ``("tcp"|"udp", port,
        packets)``, most first. A packet counts for the lower of its two ports
        (the server's, as a rule: servers listen on low ports, clients on
        ephemeral ones); at most :data:`MAX_PORTS` distinct ports are counted."""
        top = heapq.nlargest(n, self._ports.items(), key=lambda item: (item[1], -item[0]))
        return [("udp" if key & _UDP_PORT else "tcp", key & 0xFFFF, count) for key, count in top]

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

    def _other_port(self, key: int) -> None:
        ports = self._ports
        count = ports.get(key)
        if count is not None:
            ports[key] = count + 1
        elif len(ports) < MAX_PORTS:
            ports[key] = 1
        else:
            self.other_ports_dropped += 1

    def _stream(self, transport: Transport, client: str, server: str) -> Stream:
        if self.new_stream is not None:
            stream = self.new_stream(transport, client, server)
        else:
            stream = Stream(self.next_id, transport, client, server)
        self.next_id += 1
        return stream

    def packet(
        self, ts: float, link: int, iface: int, buf: bytes, off: int, end: int, out: list[Any]
    ) -> None:
        """Dissect one record (``buf[off:end]``, link type ``link``, captured at ``ts``
        on interface ``iface``); append the chunks and events it causes to ``out``.

        The fast form for file pumps and the fused reader: no list per packet. Time
        moves on with the packets: timeouts due by ``ts`` are handled first.
        """
        if ts >= self._due:
            self._tick(ts, out)
        if link == 1 and end - off >= 54:
            # Fast path for the common case, Ethernet + IPv4 without options + TCP,
            # in one unpack; anything else takes the general path below.
            et, vihl, total, frag, proto, addrs, sport, dport, seq, ack, hl = _eth_ipv4_tcp(
                buf, off
            )
            ip_end = off + 14 + total
            doff = (hl >> 10) & 0x3C
            if (
                et == 0x0800
                and vihl == 0x45
                and proto == 6
                and not frag & 0x3FFF
                and 40 <= total
                and ip_end <= end
                and 20 <= doff <= total - 20
            ):
                # whole headers and a whole IP packet: anything else (a cut, a
                # length the capture left out, a bad offset) is the general path's
                self.good_ts = ts
                ports = self.ports
                if sport not in ports and dport not in ports:
                    if self.detector is not None:
                        payload = buf[off + 34 + doff : ip_end]
                        self._detect(ts, (addrs, sport, dport), seq, ack, hl & 0xFF, payload, out)
                        return
                    self.non_modbus += 1
                    self._other_port(sport if sport < dport else dport)
                    return
                self.modbus_packets += 1
                flags = hl & 0xFF
                key = (addrs, sport, dport)
                flow = self.tcp.get(key)
                payload = buf[off + 34 + doff : ip_end]
                if flow is None or flags & SYN or flow[0].closed:
                    flow = self._tcp_flow(key, flow, ts, seq, flags, bool(payload), out)
                flow[0].segment(ts, flow[1], seq, ack, flags, payload, out)
                return
        self._general(ts, link, iface, buf, off, end, out)

    def packet_general(
        self, ts: float, link: int, iface: int, buf: bytes, off: int, end: int, out: list[Any]
    ) -> None:
        """:meth:`packet` without its Ethernet/IPv4/TCP fast path: every record the
        general way. The differential tests feed the same packets both ways and pin
        the results (chunks, events, counters) equal."""
        if ts >= self._due:
            self._tick(ts, out)
        self._general(ts, link, iface, buf, off, end, out)

    def _general(
        self, ts: float, link: int, iface: int, buf: bytes, off: int, end: int, out: list[Any]
    ) -> None:
        """Any link type, VLAN tags, IPv4 (options, fragments) or IPv6 (extension
        headers), TCP or UDP: what :meth:`packet`'s fast path does not take. Each
        layer is one method; a header that makes no sense is counted where it is
        found and ends the packet."""
        if link == 147:
            self._bus(ts, iface, buf[off:end], out)
            return
        found = link_layer(self, link, buf, off, end)
        if found is None:
            return
        et, off = found
        if et == 0x0800:
            ip = ipv4_header(self, buf, off, end)
        elif et == 0x86DD:
            ip = ipv6_header(self, buf, off, end)
        else:
            self.non_ip += 1
            return
        if ip is None:
            return
        proto, l4, ip_end, addrs, short = ip
        if proto == 6:
            self._tcp_general(ts, buf, l4, ip_end, addrs, short, out)
        elif proto == 17:
            self._udp_general(ts, buf, l4, ip_end, addrs, out)
        else:
            self.non_modbus += 1

    def _cut_transport(self, l4: int, ip_end: int, size: int) -> bool:
        """Whether a transport header of ``size`` bytes at ``l4`` is missing (counted:
        malformed when the IP header already ran past its packet, else truncated)."""
        if ip_end - l4 >= size:
            return False
        if ip_end < l4:
            self.malformed += 1
        else:
            self.truncated += 1
        return True

    def _tcp_general(
        self,
        ts: float,
        buf: bytes,
        l4: int,
        ip_end: int,
        addrs: bytes,
        short: bool,
        out: list[Any],
    ) -> None:
        """A TCP segment at ``l4`` (IP payload up to ``ip_end``, ``short``: the IP packet
        was cut): to its flow, to port detection, or counted."""
        if self._cut_transport(l4, ip_end, 20):
            return
        sport, dport, seq, ack, hl = _tcp_unpack(buf, l4)
        self.good_ts = ts
        ports = self.ports
        doff = (hl >> 10) & 0x3C
        if sport not in ports and dport not in ports:
            if self.detector is not None and not short and 20 <= doff <= ip_end - l4:
                payload = buf[l4 + doff : ip_end]
                self._detect(ts, (addrs, sport, dport), seq, ack, hl & 0xFF, payload, out)
                return
            self.non_modbus += 1
            self._other_port(sport if sport < dport else dport)
            return
        self.modbus_packets += 1
        if doff < 20:
            self.malformed += 1
            return
        if l4 + doff > ip_end:
            self.truncated += 1
            return
        flags = hl & 0xFF
        key = (addrs, sport, dport)
        flow = self.tcp.get(key)
        payload = buf[l4 + doff : ip_end]
        if flow is None or flags & SYN or flow[0].closed:
            flow = self._tcp_flow(key, flow, ts, seq, flags, bool(payload), out)
        flow[0].segment(ts, flow[1], seq, ack, flags, payload, out)
        if short:
            self.truncated += 1

    def _udp_general(
        self, ts: float, buf: bytes, l4: int, ip_end: int, addrs: bytes, out: list[Any]
    ) -> None:
        """A UDP datagram at ``l4`` (IP payload up to ``ip_end``): a chunk of its
        stream, or counted."""
        if self._cut_transport(l4, ip_end, 8):
            return
        sport, dport, ulen = _udp_unpack(buf, l4)
        self.good_ts = ts
        ports = self.ports
        if sport not in ports and dport not in ports:
            self.non_modbus += 1
            self._other_port(_UDP_PORT | (sport if sport < dport else dport))
            return
        self.modbus_packets += 1
        if ulen < 8:
            self.malformed += 1
            return
        if l4 + ulen > ip_end:  # cut, or a first fragment: half a datagram is none
            self.truncated += 1
            return
        if ulen == 8:
            return
        key = (addrs, sport, dport)
        dgram = self.udp.get(key)
        if dgram is None:
            if len(self._udp_last) >= self.max_flows:
                self._evict_udp(ts, out)
            dgram = self._new_udp(key, ts)
        self._udp_last[dgram[0].id] = ts
        out.append(make_chunk(ts, dgram[0], dgram[1], buf[l4 + 8 : l4 + ulen]))

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
        src, dst = _address(addrs[:half], sport), _address(addrs[half:], dport)
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

    def _detect(
        self, ts: float, key: Key, seq: int, ack: int, flags: int, payload: bytes, out: list[Any]
    ) -> None:
        """A TCP segment on no Modbus port while port detection is on: a stream's
        when its connection (or its server endpoint) was found to be Modbus,
        else the detector's to judge; a promotion replays what it held."""
        detector = self.detector
        assert detector is not None
        flow = self.tcp.get(key)
        if flow is None and not detector.serves(key):
            verdict = detector.segment(ts, key, seq, ack, flags, payload)
            if verdict is True:
                self.non_modbus += 1  # held; counted as Modbus if it is promoted
            elif verdict is False:
                self.non_modbus += 1
                self._other_port(key[1] if key[1] < key[2] else key[2])
            else:
                self._promote(verdict, out)
            return
        self.modbus_packets += 1
        if flow is None or flags & SYN or flow[0].closed:
            flow = self._tcp_flow(key, flow, ts, seq, flags, bool(payload), out)
        flow[0].segment(ts, flow[1], seq, ack, flags, payload, out)

    def _promote(self, promotion: Promotion, out: list[Any]) -> None:
        """A connection proved Modbus: its held segments go through reassembly in
        capture order, as if its port had been named from the start."""
        self.non_modbus -= len(promotion.segments) - 1
        self.modbus_packets += len(promotion.segments)
        tcp = self.tcp
        for ts, key, seq, ack, flags, payload in promotion.segments:
            flow = tcp.get(key)
            if flow is None or flags & SYN or flow[0].closed:
                flow = self._tcp_flow(key, flow, ts, seq, flags, bool(payload), out)
            flow[0].segment(ts, flow[1], seq, ack, flags, payload, out)

    def detected(self) -> list[tuple[str, int, str, int]]:
        """What port detection found (empty when it is off): ``(transport value,
        port, server address, streams)`` per server endpoint, in order found."""
        if self.detector is None:
            return []
        return [
            (transport, port, _address(address, port), streams)
            for transport, port, address, streams in self.detector.found()
        ]

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

    def _bus(self, ts: float, iface: int, data: bytes, out: list[Any]) -> None:
        """Link type 147: each record is bytes read from one RS485 bus (RTU)."""
        self.bus_records += 1
        self.good_ts = ts
        stream = self.buses.get(iface)
        if stream is None:
            stream = self._new_bus(iface, ts, out)
        self._bus_last[iface] = ts
        if data:
            out.append(make_chunk(ts, stream, Direction.BUS, data))

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
