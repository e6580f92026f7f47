"""Packets that mbmon writes into captures: link-layer frames for every link type
the reader dissects (:func:`link_frame`), IPv4/IPv6/TCP/UDP headers with valid
checksums, and :class:`TcpConversation`, which keeps sequence and acknowledgement
numbers consistent over a whole connection so that Wireshark shows no analysis
warnings.

Pure Python, no scapy. The capture files these frames go into are
:mod:`mbmon.io.pcap.files`; chunks and events become frames in
:mod:`mbmon.io.pcap.chunks`.
"""

from __future__ import annotations

import ipaddress
import struct
from collections.abc import Sequence

LINKTYPE_NULL = 0  # BSD loopback: 4-byte address family in the writer's byte order
LINKTYPE_ETHERNET = 1
LINKTYPE_RAW = 101  # raw IPv4/IPv6, version from the first nibble
LINKTYPE_LOOP = 108  # OpenBSD loopback: 4-byte address family, big endian
LINKTYPE_LINUX_SLL = 113
LINKTYPE_USER0 = 147  # mbmon: one record = bytes read from an RS485 bus (Modbus RTU)
LINKTYPE_IPV4 = 228
LINKTYPE_IPV6 = 229
LINKTYPE_LINUX_SLL2 = 276

FIN = 0x01
SYN = 0x02
RST = 0x04
PSH = 0x08
ACK = 0x10

ETHERTYPE_IPV4 = 0x0800
ETHERTYPE_IPV6 = 0x86DD
ETHERTYPE_VLAN = 0x8100
ETHERTYPE_QINQ = 0x88A8

MODBUS_PORT = 502  # the port Wireshark decodes as Modbus/TCP and Modbus/UDP


def parse_endpoint(endpoint: str) -> tuple[str, int]:
    """Split ``IP:PORT`` or ``[IPv6]:PORT`` (the form :class:`mbmon.model.Stream` uses)."""
    if endpoint.startswith("["):
        host, _, port = endpoint[1:].partition("]:")
    else:
        host, _, port = endpoint.rpartition(":")
    return host, int(port)


def join_endpoint(host: str, port: int) -> str:
    """``IP:PORT``, or ``[IPv6]:PORT``: the inverse of :func:`parse_endpoint`."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _packed(address: str) -> bytes:
    return ipaddress.ip_address(address).packed


def _checksum(data: bytes) -> int:
    if len(data) % 2:
        data += b"\0"
    total = sum(struct.unpack(f"!{len(data) // 2}H", data))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


def _pseudo_header(src: bytes, dst: bytes, proto: int, length: int) -> bytes:
    if len(src) == 4:
        return src + dst + struct.pack("!BBH", 0, proto, length)
    return src + dst + struct.pack("!IxxxB", length, proto)


def tcp_header(
    src: str,
    dst: str,
    sport: int,
    dport: int,
    seq: int,
    ack: int,
    flags: int,
    payload: bytes = b"",
    *,
    window: int = 65535,
) -> bytes:
    """A TCP segment (20-byte header + payload) with a valid checksum."""
    header = struct.pack(
        "!HHIIBBHHH", sport, dport, seq & 0xFFFFFFFF, ack & 0xFFFFFFFF, 5 << 4, flags, window, 0, 0
    )
    segment = header + payload
    csum = _checksum(_pseudo_header(_packed(src), _packed(dst), 6, len(segment)) + segment)
    return segment[:16] + struct.pack("!H", csum) + segment[18:]


def udp_header(src: str, dst: str, sport: int, dport: int, payload: bytes = b"") -> bytes:
    """A UDP datagram (8-byte header + payload) with a valid checksum."""
    length = 8 + len(payload)
    datagram = struct.pack("!HHHH", sport, dport, length, 0) + payload
    csum = _checksum(_pseudo_header(_packed(src), _packed(dst), 17, length) + datagram) or 0xFFFF
    return datagram[:6] + struct.pack("!H", csum) + datagram[8:]


def ipv4_packet(
    src: str,
    dst: str,
    proto: int,
    payload: bytes,
    *,
    ident: int = 0,
    ttl: int = 64,
    flags_fragment: int = 0x4000,
    options: bytes = b"",
) -> bytes:
    """An IPv4 packet; ``flags_fragment`` is the raw flags+offset word (default DF)."""
    ihl = 5 + len(options) // 4
    header = (
        struct.pack(
            "!BBHHHBBH4s4s",
            0x40 | ihl,
            0,
            ihl * 4 + len(payload),
            ident,
            flags_fragment,
            ttl,
            proto,
            0,
            _packed(src),
            _packed(dst),
        )
        + options
    )
    csum = _checksum(header)
    return header[:10] + struct.pack("!H", csum) + header[12:] + payload


def ipv6_packet(
    src: str,
    dst: str,
    next_header: int,
    payload: bytes,
    *,
    hop_limit: int = 64,
    extensions: Sequence[tuple[int, bytes]] = (),
) -> bytes:
    """An IPv6 packet. ``extensions`` are ``(header type, body)`` pairs, in order; the
    body is what follows the next-header and length bytes (hop-by-hop, routing,
    destination options: padded to 8 bytes) or the fragment header's 6 bytes."""
    chain = b""
    types = [t for t, _ in extensions] + [next_header]
    for i, (htype, body) in enumerate(extensions):
        nxt = types[i + 1]
        if htype == 44:  # fragment header: fixed 8 bytes, reserved length byte
            chain += struct.pack("!BB", nxt, 0) + body[:6].ljust(6, b"\0")
        elif htype == 51:  # AH: length in 4-byte units minus 2
            body = body + b"\0" * (-(len(body) + 2) % 4)
            chain += struct.pack("!BB", nxt, (len(body) + 2) // 4 - 2) + body
        else:
            body = body + b"\0" * (-(len(body) + 2) % 8)
            chain += struct.pack("!BB", nxt, (len(body) + 2) // 8 - 1) + body
    first = types[0]
    return (
        struct.pack("!IHBB", 6 << 28, len(chain) + len(payload), first, hop_limit)
        + _packed(src)
        + _packed(dst)
        + chain
        + payload
    )


def ip_packet(src: str, dst: str, proto: int, payload: bytes) -> bytes:
    """IPv4 or IPv6 by the address family of ``src``."""
    if ":" in src:
        return ipv6_packet(src, dst, proto, payload)
    return ipv4_packet(src, dst, proto, payload)


def mac_for(address: str) -> bytes:
    """A stable locally administered MAC derived from an IP address."""
    packed = _packed(address)
    return b"\x02" + packed[-5:].rjust(5, b"\0")


def ethernet_frame(
    payload: bytes,
    ethertype: int,
    *,
    src: bytes = b"\x02\0\0\0\0\x01",
    dst: bytes = b"\x02\0\0\0\0\x02",
    vlans: Sequence[tuple[int, int]] = (),
) -> bytes:
    """An Ethernet II frame; ``vlans`` are ``(tpid, vlan id)`` tags, outermost first."""
    tags = b"".join(struct.pack("!HH", tpid, vid & 0x0FFF) for tpid, vid in vlans)
    return dst + src + tags + struct.pack("!H", ethertype) + payload


def link_frame(
    linktype: int,
    ip: bytes,
    *,
    src_mac: bytes = b"\x02\0\0\0\0\x01",
    dst_mac: bytes = b"\x02\0\0\0\0\x02",
    vlans: Sequence[tuple[int, int]] = (),
    null_big_endian: bool = False,
) -> bytes:
    """Wrap an IP packet in the link layer of ``linktype`` (every type the reader dissects)."""
    v6 = (ip[0] >> 4) == 6
    ethertype = ETHERTYPE_IPV6 if v6 else ETHERTYPE_IPV4
    if linktype == LINKTYPE_ETHERNET:
        return ethernet_frame(ip, ethertype, src=src_mac, dst=dst_mac, vlans=vlans)
    if linktype in (LINKTYPE_RAW, 12, 14, LINKTYPE_IPV4, LINKTYPE_IPV6):
        return ip
    if linktype in (LINKTYPE_NULL, LINKTYPE_LOOP):
        family = 24 if v6 else 2  # AF_INET6 as on most BSDs, AF_INET
        big = null_big_endian or linktype == LINKTYPE_LOOP
        return struct.pack(">I" if big else "<I", family) + ip
    if linktype == LINKTYPE_LINUX_SLL:
        # packet type 0 (to us), ARPHRD_ETHER, address length 6, address (8 bytes), protocol
        return struct.pack("!HHH8sH", 0, 1, 6, src_mac, ethertype) + ip
    if linktype == LINKTYPE_LINUX_SLL2:
        # protocol, reserved, interface index, ARPHRD_ETHER, packet type, addr len, addr
        return struct.pack("!HHIHBB8s", ethertype, 0, 1, 1, 0, 6, src_mac) + ip
    raise ValueError(f"link type {linktype} cannot carry IP in this writer")


def tcp_frame(
    linktype: int,
    src: str,
    dst: str,
    sport: int,
    dport: int,
    seq: int,
    ack: int,
    flags: int,
    payload: bytes = b"",
    **link: object,
) -> bytes:
    """One TCP segment as a complete link-layer frame."""
    segment = tcp_header(src, dst, sport, dport, seq, ack, flags, payload)
    return link_frame(linktype, ip_packet(src, dst, 6, segment), **link)  # type: ignore[arg-type]


def udp_frame(
    linktype: int, src: str, dst: str, sport: int, dport: int, payload: bytes, **link: object
) -> bytes:
    """One UDP datagram as a complete link-layer frame."""
    datagram = udp_header(src, dst, sport, dport, payload)
    return link_frame(linktype, ip_packet(src, dst, 17, datagram), **link)  # type: ignore[arg-type]


class TcpConversation:
    """Frames of one TCP connection with consistent sequence and ack numbers.

    ``client`` and ``server`` are ``IP:PORT`` strings (``[v6]:port`` too). Every
    method returns finished link-layer frames for ``linktype``; the conversation
    tracks ``client_next``/``server_next`` (the next sequence number each side
    sends) and acknowledges everything the other side sent. Tests may set the
    counters directly to fabricate holes or retransmissions.
    """

    def __init__(
        self,
        client: str,
        server: str,
        *,
        client_isn: int = 1000,
        server_isn: int = 5000,
        linktype: int = LINKTYPE_ETHERNET,
        vlans: Sequence[tuple[int, int]] = (),
    ) -> None:
        self.client_ip, self.client_port = parse_endpoint(client)
        self.server_ip, self.server_port = parse_endpoint(server)
        self.client_isn = client_isn & 0xFFFFFFFF
        self.server_isn = server_isn & 0xFFFFFFFF
        self.client_next = (client_isn + 1) & 0xFFFFFFFF
        self.server_next = (server_isn + 1) & 0xFFFFFFFF
        self.linktype = linktype
        self.vlans = tuple(vlans)
        self._client_mac = mac_for(self.client_ip)
        self._server_mac = mac_for(self.server_ip)

    def segment(
        self,
        from_client: bool,
        flags: int,
        payload: bytes = b"",
        *,
        seq: int | None = None,
        ack: int | None = None,
        advance: bool = True,
    ) -> bytes:
        """One segment; by default at the sender's next sequence number, which then
        moves past the payload (and past SYN/FIN, which take one number each)."""
        if from_client:
            src, sport, dst, dport = (
                self.client_ip,
                self.client_port,
                self.server_ip,
                self.server_port,
            )
            own, other = self.client_next, self.server_next
            src_mac, dst_mac = self._client_mac, self._server_mac
        else:
            src, sport, dst, dport = (
                self.server_ip,
                self.server_port,
                self.client_ip,
                self.client_port,
            )
            own, other = self.server_next, self.client_next
            src_mac, dst_mac = self._server_mac, self._client_mac
        seq = own if seq is None else seq
        ack = (other if flags & ACK else 0) if ack is None else ack
        frame = tcp_frame(
            self.linktype,
            src,
            dst,
            sport,
            dport,
            seq,
            ack,
            flags,
            payload,
            src_mac=src_mac,
            dst_mac=dst_mac,
            vlans=self.vlans,
        )
        if advance:
            end = (seq + len(payload) + (1 if flags & (SYN | FIN) else 0)) & 0xFFFFFFFF
            if from_client:
                self.client_next = end
            else:
                self.server_next = end
        return frame

    def open(self) -> list[bytes]:
        """The three-way handshake: SYN, SYN-ACK, ACK."""
        self.client_next = self.client_isn
        self.server_next = self.server_isn
        syn = self.segment(True, SYN)
        syn_ack = self.segment(False, SYN | ACK)
        return [syn, syn_ack, self.segment(True, ACK)]

    def send(self, from_client: bool, payload: bytes) -> bytes:
        """One data segment (PSH|ACK) carrying ``payload``."""
        return self.segment(from_client, PSH | ACK, payload)

    def ack(self, from_client: bool) -> bytes:
        """A pure ACK of everything the other side sent."""
        return self.segment(from_client, ACK)

    def close(self, from_client: bool = True) -> list[bytes]:
        """Orderly close started by one side: FIN-ACK, FIN-ACK, ACK."""
        first = self.segment(from_client, FIN | ACK)
        second = self.segment(not from_client, FIN | ACK)
        return [first, second, self.segment(from_client, ACK)]

    def reset(self, from_client: bool) -> bytes:
        """An abortive close (RST-ACK) from one side."""
        return self.segment(from_client, RST | ACK, advance=False)
