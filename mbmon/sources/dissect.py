"""Packets in, Modbus byte streams out: the dissector every packet source shares.

This module owns what happens to one captured packet, whatever read it (a
capture file, :mod:`mbmon.sources.pcapfile`; a live raw socket, scapy as a byte
source): the link layer (Ethernet, VLAN tags, Linux cooked v1/v2, raw IP, BSD
loopback, USER0 = an RTU bus), IPv4/IPv6 (options, extension headers,
fragments counted), TCP/UDP, deciding which packets are Modbus (by port,
:class:`CaptureConfig`), naming streams, reassembly of TCP
(:mod:`mbmon.sources.tcpflow`) and, through :mod:`mbmon.sources.flows`, the
lifetime of every piece of per-flow state. The output is :class:`~mbmon.model.Chunk` and
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

State is bounded, so a run can last weeks: the flows, their streams and the
lifetime of their state (closed connections' linger, :data:`CLOSED_LINGER` and
:data:`MAX_CLOSED`; idle expiry; eviction past ``max_flows``; hole timeouts)
are :class:`mbmon.sources.flows.FlowTable`'s, the base of :class:`Dissector`;
the non-Modbus port counter (:meth:`Dissector.busiest_ports`) keeps at most
:data:`MAX_PORTS` ports.

Time is the packets' own: :meth:`Dissector.packet` first handles what fell due
by the packet's timestamp; :meth:`Dissector.tick` moves time on while no packet
arrives (a live source's clock); :meth:`Dissector.next_deadline` says when that
is next needed. Chunks carry the capture time of the packet that carried their
bytes, also when they were held behind a hole.
"""

from __future__ import annotations

import heapq
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from mbmon.model import Chunk, Direction, Event, Stream, Transport
from mbmon.sources.flows import (
    CLOSED_LINGER,
    MAX_CLOSED,
    MAX_FLOWS,
    FlowTable,
    Key,
    address_text,
)
from mbmon.sources.headers import ipv4_header, ipv6_header, link_layer
from mbmon.sources.tcpflow import SYN, make_chunk

if TYPE_CHECKING:
    from mbmon.analysis.detect import PortDetector, Promotion

__all__ = ["CLOSED_LINGER", "MAX_CLOSED", "MAX_FLOWS", "MAX_PORTS", "CaptureConfig", "Dissector"]

#: Distinct non-Modbus ports counted at most (later new ports are not counted).
MAX_PORTS = 4096
_UDP_PORT = 0x10000  # port counter key bit: UDP (else TCP)


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


_tcp_unpack = struct.Struct("!HHIIH").unpack_from
_udp_unpack = struct.Struct("!HHH").unpack_from
# Ethernet type, IPv4 (version/IHL, length, flags/offset, protocol, addresses), TCP
_eth_ipv4_tcp = struct.Struct("!12xHBxHxxHxBxx8sHHIIH").unpack_from


class Dissector(FlowTable):
    """From link-layer packets to chunks and events; stream identity and the
    lifetime of every flow's state are its base's, :class:`~mbmon.sources.flows.FlowTable`
    (see the module docstring).

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
        detector: PortDetector | None = None
        if config.detect:
            from mbmon.analysis.detect import PortDetector

            detector = PortDetector()
        super().__init__(
            config.tcp_ports | config.rtu_ports,
            config.rtu_ports,
            detector,
            bus_name,
            new_stream=new_stream,
            idle_timeout=idle_timeout,
            hole_timeout=hole_timeout,
            max_flows=max_flows,
        )
        self._ports: dict[int, int] = {}  # non-Modbus port (| _UDP_PORT) -> packets
        # time of the last packet that parsed (up to TCP/UDP, or a bus record): the
        # last good time when a damaged file ends (garbled records have no time)
        self.good_ts: float | None = None
        self.modbus_packets = 0
        self.non_modbus = 0
        self.non_ip = 0
        self.truncated = 0
        self.fragments = 0
        self.malformed = 0
        self.unsupported_link = 0
        self.bus_records = 0
        self.other_ports_dropped = 0  # non-Modbus packets whose port was not counted

    # ------------------------------------------------------------------ API

    def packet_bytes(self, ts: float, linktype: int, data: bytes) -> list[Chunk | Event]:
        """Dissect one packet of link type ``linktype`` captured at ``ts`` (a live
        capture's form of :meth:`packet`): the chunks and events it causes."""
        out: list[Any] = []
        self.packet(ts, linktype, 0, data, 0, len(data), out)
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

    def _other_port(self, key: int) -> None:
        ports = self._ports
        count = ports.get(key)
        if count is not None:
            ports[key] = count + 1
        elif len(ports) < MAX_PORTS:
            ports[key] = 1
        else:
            self.other_ports_dropped += 1

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
            (transport, port, address_text(address, port), streams)
            for transport, port, address, streams in self.detector.found()
        ]

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
