"""Pcap and pcapng writers plus packet builders with consistent TCP numbering.

This module owns the byte layout of what mbmon writes as captures: the classic
pcap file (:class:`PcapWriter`), pcapng (:class:`PcapngWriter`, used by the tests
to cover every block type the reader accepts), link-layer wrappers for every
link type the reader dissects (:func:`link_frame`), IPv4/IPv6/TCP/UDP headers
with valid checksums, and :class:`TcpConversation`, which keeps sequence and
acknowledgement numbers consistent over a whole connection so that Wireshark
shows no analysis warnings. :class:`ChunkWriter` is mbmon's one pcap writer: it
turns chunks and events back into such a capture (``-w x.pcap`` and ``export -o
x.pcap`` through :class:`mbmon.sinks.pcap.PcapSink`, a thin listener over it):
one conversation per TCP stream (optionally one ADU per segment), datagrams for
UDP, link type 147 records for RTU bus bytes; reading its output with
:func:`mbmon.sources.pcapfile.read_capture` gives the same chunks and events.

Pure Python, no scapy.
"""

from __future__ import annotations

import datetime
import ipaddress
import struct
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO, Self

from mbmon.model import Chunk, Direction, Event, EventKind, Frame, Stream, Transport
from mbmon.timefmt import epoch_text

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

_PCAP_MAGIC_US = 0xA1B2C3D4
_PCAP_MAGIC_NS = 0xA1B23C4D


def _utc_text(ts: float) -> str:
    """``ts`` as a UTC date and time with microseconds (epoch seconds out of range)."""
    try:
        when = datetime.datetime.fromtimestamp(ts, datetime.UTC)
    except (ValueError, OverflowError, OSError):
        return f"{epoch_text(ts)} s"
    return when.strftime("%Y-%m-%d %H:%M:%S.%f UTC")


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


class _CaptureFile:
    """The output file of a capture writer: a path (opened and closed here) or a
    binary file object (flushed, and left open for its owner, on :meth:`close`)."""

    def __init__(self, out: str | Path | BinaryIO) -> None:
        if isinstance(out, str | Path):
            self._f: BinaryIO = open(out, "wb")
            self._own = True
        else:
            self._f = out
            self._own = False

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        if self._own:
            self._f.close()
        else:
            self._f.flush()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class PcapWriter(_CaptureFile):
    """Classic pcap file with one link type (micro- or nanosecond timestamps).

    ``out`` is a path or a binary file object (left open on :meth:`close` when it
    was given as an object). Records longer than ``snaplen`` are cut to it.
    """

    def __init__(
        self,
        out: str | Path | BinaryIO,
        linktype: int = LINKTYPE_ETHERNET,
        *,
        snaplen: int = 262144,
        nanosecond: bool = False,
        big_endian: bool = False,
    ) -> None:
        super().__init__(out)
        self._e = ">" if big_endian else "<"
        self._scale = 1_000_000_000 if nanosecond else 1_000_000
        self._snaplen = snaplen
        self._rec = struct.Struct(self._e + "IIII")
        magic = _PCAP_MAGIC_NS if nanosecond else _PCAP_MAGIC_US
        self._f.write(struct.pack(self._e + "IHHiIII", magic, 2, 4, 0, 0, snaplen, linktype))

    def write(self, ts: float, data: bytes, *, orig_len: int | None = None) -> None:
        """One record at ``ts`` (epoch seconds); ``orig_len`` defaults to ``len(data)``."""
        units = round(ts * self._scale)
        sec, frac = divmod(units, self._scale)
        cap = data[: self._snaplen]
        self._f.write(
            self._rec.pack(sec, frac, len(cap), len(data) if orig_len is None else orig_len)
        )
        self._f.write(cap)


class PcapngWriter(_CaptureFile):
    """Pcapng file: sections, interfaces, and every packet block type (EPB, SPB, PB).

    Interfaces are added with :meth:`add_interface` (returns the interface id);
    ``tsresol`` is the raw ``if_tsresol`` option byte (6 = microseconds, the
    default; 9 = nanoseconds; 0x80 | n = 2^-n seconds).
    """

    def __init__(
        self, out: str | Path | BinaryIO, *, big_endian: bool = False, comments: Sequence[str] = ()
    ) -> None:
        super().__init__(out)
        self._e = ">" if big_endian else "<"
        self._ifaces: list[tuple[int, int]] = []  # (resolution divisor, snaplen)
        self.new_section(comments=comments)

    def _block(self, block_type: int, body: bytes) -> None:
        body += b"\0" * (-len(body) % 4)
        total = len(body) + 12
        self._f.write(struct.pack(self._e + "II", block_type, total) + body)
        self._f.write(struct.pack(self._e + "I", total))

    def _option(self, code: int, value: bytes) -> bytes:
        return struct.pack(self._e + "HH", code, len(value)) + value + b"\0" * (-len(value) % 4)

    def _comments(self, comments: Sequence[str]) -> bytes:
        """One ``opt_comment`` (option 1, UTF-8) per comment; the end-of-options
        marker is the caller's."""
        return b"".join(self._option(1, text.encode("utf-8")) for text in comments)

    def _section_header(self, comments: Sequence[str] = ()) -> bytes:
        """The SHB body: byte-order magic, version 1.0, unknown section length,
        ``shb_comment`` for each of ``comments``, ``shb_userappl`` mbmon."""
        body = struct.pack(self._e + "IHHq", 0x1A2B3C4D, 1, 0, -1)
        return body + self._comments(comments) + self._option(4, b"mbmon") + self._option(0, b"")

    def new_section(self, *, big_endian: bool | None = None, comments: Sequence[str] = ()) -> None:
        """Start a section (SHB, with a ``shb_comment`` for each of ``comments``);
        interfaces of earlier sections are forgotten."""
        if big_endian is not None:
            self._e = ">" if big_endian else "<"
        self._ifaces = []
        self._block(0x0A0D0D0A, self._section_header(comments))

    @staticmethod
    def comment_first_section(path: str | Path, comments: Sequence[str]) -> None:
        """Give the first section of the finished pcapng file ``path`` the
        ``shb_comment`` options ``comments`` (replacing its header, which must be
        one this writer wrote); the file is rewritten beside itself and renamed over,
        so a failure leaves the original whole. What a file says about itself is
        known only once it is written: the writer starts it with a plain header so
        that a live capture is readable from its first packet."""
        path = Path(path)
        with open(path, "rb") as f:
            head = f.read(12)
            if len(head) < 12 or head[:4] != b"\x0a\x0d\x0d\x0a":
                raise ValueError(f"{path}: not a pcapng file")
            e = "<" if head[8:12] == b"\x4d\x3c\x2b\x1a" else ">"
            (length,) = struct.unpack(e + "I", head[4:8])
            f.seek(length)
            tmp = path.with_name(path.name + ".tmp")
            try:
                with open(tmp, "wb") as out:
                    PcapngWriter(out, big_endian=e == ">", comments=comments)
                    while block := f.read(1 << 20):
                        out.write(block)
                tmp.replace(path)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise

    def add_interface(
        self,
        linktype: int,
        *,
        snaplen: int = 0,
        tsresol: int | None = None,
        tsoffset: int | None = None,
    ) -> int:
        """An IDB; returns its interface id within the current section."""
        options = b""
        if tsresol is not None:
            options += self._option(9, bytes([tsresol]))
        if tsoffset is not None:
            options += self._option(14, struct.pack(self._e + "q", tsoffset))
        if options:
            options += self._option(0, b"")
        self._block(1, struct.pack(self._e + "HHI", linktype, 0, snaplen) + options)
        resol = 6 if tsresol is None else tsresol
        divisor = 2 ** (resol & 0x7F) if resol & 0x80 else 10**resol
        self._ifaces.append((divisor, snaplen))
        return len(self._ifaces) - 1

    def _units(self, interface: int, ts: float, tsoffset: int = 0) -> int:
        return round((ts - tsoffset) * self._ifaces[interface][0])

    def write(
        self,
        ts: float,
        data: bytes,
        *,
        interface: int = 0,
        orig_len: int | None = None,
        tsoffset: int = 0,
        comments: Sequence[str] = (),
    ) -> None:
        """An Enhanced Packet Block (``tsoffset``: the interface's if_tsoffset, if set;
        ``comments``: an ``opt_comment`` each, what Wireshark shows as the packet's
        comments, ``frame.comment``)."""
        units = self._units(interface, ts, tsoffset)
        head = struct.pack(
            self._e + "IIIII",
            interface,
            units >> 32,
            units & 0xFFFFFFFF,
            len(data),
            len(data) if orig_len is None else orig_len,
        )
        body = head + data + b"\0" * (-len(data) % 4)
        if comments:
            body += self._comments(comments) + self._option(0, b"")
        self._block(6, body)

    def write_simple(self, data: bytes, *, orig_len: int | None = None) -> None:
        """A Simple Packet Block (interface 0, no timestamp)."""
        self._block(
            3, struct.pack(self._e + "I", len(data) if orig_len is None else orig_len) + data
        )

    def write_obsolete(self, ts: float, data: bytes, *, interface: int = 0) -> None:
        """An obsolete Packet Block (type 2)."""
        units = self._units(interface, ts)
        head = struct.pack(
            self._e + "HHIIII", interface, 0, units >> 32, units & 0xFFFFFFFF, len(data), len(data)
        )
        self._block(2, head + data)

    def write_block(self, block_type: int, body: bytes) -> None:
        """Any other block (name resolution, statistics, custom...) as raw body bytes."""
        self._block(block_type, body)


class ChunkWriter:
    """Chunks and events back into a capture that :func:`read_capture` reads as the
    same chunks and events: the one pcap writer (``-w x.pcap``, ``export -o x.pcap``).

    TCP streams become Ethernet/IP/TCP conversations with consistent numbers: a
    CONNECT event writes the three-way handshake, each chunk one segment (cut in
    pieces of at most 32 KiB), a GAP skips its bytes (the peer then acknowledges
    them, so a re-read reports the same gap), a DISCONNECT writes FIN-FIN-ACK or a
    RST from the side that sent it (an idle expiry, where the dissector merely
    stopped watching a quiet flow, writes nothing). UDP chunks become datagrams; RTU bus chunks
    become link type 147 records. Other events are not packets and are skipped.
    Stream endpoints that are not ``IP:PORT`` get made-up addresses derived from
    the stream id.

    ``adu_segments``: Modbus/TCP streams are written one ADU per TCP segment
    (framed by :class:`~mbmon.protocol.mbap.MbapDecoder`; bytes it cannot frame
    become segments of their own, in order), each at the time of the chunk that
    carried its last byte, so that Wireshark dissects every ADU even where the
    original segmentation split an MBAP header. Every byte is written once. A
    GAP (bytes the capture lost) is then no hole in the sequence numbers: with
    one ADU per segment there is nothing to reassemble, and a hole would stop
    Wireshark's reassembly for the rest of the connection; the segments are
    numbered contiguously and the loss is listed in :attr:`losses`. RTU bus
    streams are written one frame per link type 147 record (framed by
    :class:`~mbmon.protocol.rtu.RtuDecoder` with ``baudrate`` and ``silence``, as
    the pipeline frames them; each run of noise a record of its own), at the
    frame's own time, so that a serial read holding a request and its answer
    becomes two records Wireshark decodes.

    ``server_port``: the server port of every Modbus/TCP and Modbus/UDP stream
    is written as this port (502: what Wireshark decodes as Modbus with no
    option); :attr:`ports_rewritten` maps each original port to it. Server
    ports written as they were and that Wireshark does not decode as Modbus by
    itself (not 502, or RTU carried over TCP/UDP) are in :attr:`ports_kept`.

    A pcap file has one link type, so with ``pcapng=False`` the first chunk fixes
    it (Ethernet, or 147 for a bus) and a chunk needing the other goes to the file
    ``companion(linktype)`` names, or raises ValueError without one; pcapng holds
    both (one interface per bus). A capture time the file cannot hold (negative,
    beyond 2106 for pcap, NaN...) is written as the previous packet's time and
    counted in :attr:`bad_times` (the first in :attr:`first_bad_time`).
    """

    MAX_SEGMENT = 32768  # larger chunks are cut into several segments (IPv4 length limit)
    NOISE_SEGMENT = 7  # unframable bytes (adu_segments): too short for an MBAP header

    def __init__(
        self,
        out: str | Path | BinaryIO,
        *,
        pcapng: bool = False,
        nanosecond: bool = True,
        adu_segments: bool = False,
        companion: Callable[[int], str | Path] | None = None,
        server_port: int | None = None,
        baudrate: int | None = None,
        silence: float | None = None,
    ) -> None:
        self._out = out
        self._nanosecond = nanosecond
        self._pcapng: PcapngWriter | None = PcapngWriter(out) if pcapng else None
        self._pcap: PcapWriter | None = None
        self._pcap_link: int | None = None
        self._other: PcapWriter | None = None
        self._companion = companion
        self.companion_path: Path | None = None
        self._ether_iface: int | None = None
        self._bus_ifaces: dict[int, int] = {}
        self._tcp: dict[int, TcpConversation] = {}
        self._adu_segments = adu_segments
        self._server_port = server_port
        self._baudrate = baudrate
        self._silence = silence
        self._bus_framers: dict[int, Any] = {}  # stream id -> its RtuDecoder, with adu_segments
        self._ends: dict[int, tuple[str, str]] = {}  # stream id -> endpoints as written
        #: (transport, original server port) -> the port written instead
        self.ports_rewritten: dict[tuple[Transport, int], int] = {}
        #: (transport, server port) written as they were, that Wireshark does not
        #: decode as Modbus with no option
        self.ports_kept: set[tuple[Transport, int]] = set()
        # (transport, host, port as written) -> the port it stands for: two servers of
        # one host (a proxy's own answers beside its robot's) never become one endpoint
        self._claimed: dict[tuple[Transport, str, int], int] = {}
        #: bytes the capture lost, numbered over (adu_segments): (time, stream,
        #: direction value, bytes), in order
        self.losses: list[tuple[float, Stream, str, int]] = []
        #: link type 147 records written (RTU bus bytes)
        self.bus_records = 0
        # pcapng packet comments waiting for their packet: a stream's first (its
        # server port rewritten), a direction's next segment (bytes lost before it)
        self._stream_notes: dict[int, str] = {}
        self._loss_notes: dict[tuple[int, bool], list[str]] = {}
        # (stream id, direction) -> (stream, its MBAP decoder), with adu_segments
        self._framers: dict[tuple[int, Direction], tuple[Stream, Any]] = {}
        # the range of times the file holds: pcap has 32-bit seconds; pcapng 64-bit units
        self._max_ts = 1.8e10 if pcapng else 4294967295.0
        self._last_ts = 0.0
        self.bad_times = 0
        self.first_bad_time: float | None = None

    @property
    def linktype(self) -> int | None:
        """The link type of the classic pcap file (the first packet's), ``None`` before
        the first packet or for pcapng (which holds both)."""
        return self._pcap_link

    def _time(self, ts: float) -> float:
        """``ts``, or the previous packet's time when the file cannot hold it."""
        if 0.0 <= ts < self._max_ts:
            self._last_ts = ts
            return ts
        self.bad_times += 1
        if self.first_bad_time is None:
            self.first_bad_time = ts
        return self._last_ts

    def _emit(
        self, ts: float, frame: bytes, linktype: int, stream_id: int, comments: Sequence[str] = ()
    ) -> None:
        """Write one packet of ``stream_id`` (pcapng: with ``comments``, and the
        stream's own note before them on its first packet)."""
        ts = self._time(ts)
        note = self._stream_notes.pop(stream_id, None)
        if note is not None:
            comments = [note, *comments]
        if linktype == LINKTYPE_USER0:
            self.bus_records += 1
        if self._pcapng is not None:
            if linktype == LINKTYPE_USER0:
                iface = self._bus_ifaces.get(stream_id)
                if iface is None:
                    iface = self._bus_ifaces[stream_id] = self._pcapng.add_interface(
                        LINKTYPE_USER0, tsresol=9
                    )
            else:
                if self._ether_iface is None:
                    self._ether_iface = self._pcapng.add_interface(LINKTYPE_ETHERNET, tsresol=9)
                iface = self._ether_iface
            self._pcapng.write(ts, frame, interface=iface, comments=comments)
            return
        if self._pcap is None:
            self._pcap = PcapWriter(self._out, linktype, nanosecond=self._nanosecond)
            self._pcap_link = linktype
        elif linktype != self._pcap_link:
            if self._companion is None:
                raise ValueError(
                    f"a pcap file holds one link type ({self._pcap_link}); "
                    f"link type {linktype} needs pcapng"
                )
            if self._other is None:
                self.companion_path = Path(self._companion(linktype))
                self._other = PcapWriter(self.companion_path, linktype, nanosecond=self._nanosecond)
            self._other.write(ts, frame)
            return
        self._pcap.write(ts, frame)

    def _endpoints(self, stream: Stream) -> tuple[str, str]:
        """The stream's endpoints as written: its own or made-up ones (see
        :meth:`_stream_endpoints`), the server port rewritten to ``server_port``
        for Modbus/TCP and Modbus/UDP."""
        ends = self._ends.get(stream.id)
        if ends is not None:
            return ends
        client, server = self._stream_endpoints(stream)
        host, port = parse_endpoint(server)
        mbap = stream.transport in (Transport.TCP, Transport.UDP)
        if mbap and self._server_port is not None:
            claim = self._claimed.setdefault((stream.transport, host, self._server_port), port)
            if claim != port:  # another server of this host is written there: keep this one
                self.ports_kept.add((stream.transport, port))
            elif port != self._server_port:
                self.ports_rewritten[(stream.transport, port)] = self._server_port
                self._stream_notes[stream.id] = (
                    f"mbmon: server port {port} in the original capture, written as "
                    f"{self._server_port}"
                )
                server = join_endpoint(host, self._server_port)
        elif not mbap or port != MODBUS_PORT:
            self.ports_kept.add((stream.transport, port))
        ends = self._ends[stream.id] = (client, server)
        return ends

    @staticmethod
    def _stream_endpoints(stream: Stream) -> tuple[str, str]:
        """The stream's endpoints, or made-up ones when they are not ``IP:PORT``."""
        try:
            for endpoint in (stream.client, stream.server):
                ipaddress.ip_address(parse_endpoint(endpoint)[0])
        except ValueError:
            sid = stream.id & 0xFFFF
            return (
                f"10.200.{sid >> 8}.{sid & 0xFF}:{49152 + stream.id % 16384}",
                f"10.201.{sid >> 8}.{sid & 0xFF}:502",
            )
        return stream.client, stream.server

    def _conversation(self, stream: Stream) -> TcpConversation:
        conv = self._tcp.get(stream.id)
        if conv is None:
            client, server = self._endpoints(stream)
            conv = self._tcp[stream.id] = TcpConversation(
                client,
                server,
                client_isn=(stream.id * 2654435761 + 1000) & 0xFFFFFFFF,
                server_isn=(stream.id * 2246822519 + 5000) & 0xFFFFFFFF,
            )
        return conv

    def write(self, item: Chunk | Event) -> None:
        """One chunk or event, in the order the reader produced them."""
        stream = item.stream
        if stream is None:
            return
        tcp = stream.transport in (Transport.TCP, Transport.RTU_OVER_TCP)
        if isinstance(item, Event):
            if tcp:
                if self._adu_segments:
                    # a gap ends what its own direction holds; the other one goes on
                    gap = item.kind is EventKind.GAP
                    self._flush_adus(stream, item.ts, item.info.get("direction") if gap else None)
                for frame in self._event_frames(item, stream, self._conversation(stream)):
                    self._emit(item.ts, frame, LINKTYPE_ETHERNET, stream.id)
            return
        from_client = item.direction is not Direction.S2C
        if tcp:
            if self._adu_segments and stream.transport is Transport.TCP:
                for piece, framed in self._adus(stream, item.direction, item.data, item.ts):
                    self._adu_segment(stream, from_client, piece, framed, item.ts)
            else:
                self._segments(stream, from_client, item.data, item.ts)
            return
        if stream.transport in (Transport.UDP, Transport.RTU_OVER_UDP):
            client, server = self._endpoints(stream)
            (cip, cport), (sip, sport) = parse_endpoint(client), parse_endpoint(server)
            if from_client:
                frame = udp_frame(LINKTYPE_ETHERNET, cip, sip, cport, sport, item.data)
            else:
                frame = udp_frame(LINKTYPE_ETHERNET, sip, cip, sport, cport, item.data)
            self._emit(item.ts, frame, LINKTYPE_ETHERNET, stream.id)
            return
        if self._adu_segments:  # a serial bus: one frame (or noise run) per record
            for frame in self._bus_framer(stream).feed(item.data, item.ts):
                self._emit(frame.ts, frame.raw, LINKTYPE_USER0, stream.id)
            return
        self._emit(item.ts, item.data, LINKTYPE_USER0, stream.id)  # a serial bus, as read

    def _bus_framer(self, stream: Stream) -> Any:
        """The RTU decoder that frames the records of bus ``stream`` (adu_segments)."""
        decoder = self._bus_framers.get(stream.id)
        if decoder is None:
            from mbmon.protocol.rtu import RtuDecoder

            decoder = self._bus_framers[stream.id] = RtuDecoder(
                stream, Direction.BUS, baudrate=self._baudrate, silence=self._silence
            )
        return decoder

    def _segments(self, stream: Stream, from_client: bool, data: bytes, ts: float) -> None:
        """``data`` as TCP segments of at most :attr:`MAX_SEGMENT` bytes."""
        conv = self._conversation(stream)
        comments = self._loss_notes.pop((stream.id, from_client), [])
        for start in range(0, max(len(data), 1), self.MAX_SEGMENT):
            frame = conv.send(from_client, data[start : start + self.MAX_SEGMENT])
            self._emit(ts, frame, LINKTYPE_ETHERNET, stream.id, comments)
            comments = []

    def _adu_segment(
        self, stream: Stream, from_client: bool, data: bytes, framed: bool, ts: float
    ) -> None:
        """One framed ADU as one segment; bytes the framer could not frame in segments
        of at most :attr:`NOISE_SEGMENT` bytes. Wireshark takes a segment for Modbus/TCP
        from 8 bytes on (an MBAP header with protocol id 0) and then waits for as many
        bytes as its length field says: unframable bytes that happen to look like a
        header (a response that lost its first byte) would swallow the ADUs after
        them; shorter segments are never taken for Modbus and start no reassembly."""
        if framed:
            self._segments(stream, from_client, data, ts)
            return
        for start in range(0, len(data), self.NOISE_SEGMENT):
            self._segments(stream, from_client, data[start : start + self.NOISE_SEGMENT], ts)

    def _adus(
        self, stream: Stream, direction: Direction, data: bytes, ts: float
    ) -> list[tuple[bytes, bool]]:
        """The complete ADUs (``(bytes, True)``) and unframable runs (``(bytes, False)``)
        of one direction that ``data`` ends."""
        key = (stream.id, direction)
        entry = self._framers.get(key)
        if entry is None:
            from mbmon.protocol.mbap import MbapDecoder

            decoder = MbapDecoder(
                stream, Direction.S2C if direction is Direction.S2C else Direction.C2S
            )
            entry = self._framers[key] = (stream, decoder)
        return [(item.raw, isinstance(item, Frame)) for item in entry[1].feed(data, ts)]

    def _flush_adus(self, stream: Stream, ts: float, only: object = None) -> None:
        """Write what the framers of ``stream`` hold (before a connect or close; before
        a gap, only the framer of the gap's direction, ``only``: its value)."""
        for direction in (Direction.C2S, Direction.S2C):
            if only is not None and direction.value != only:
                continue
            entry = self._framers.pop((stream.id, direction), None)
            if entry is not None:
                for item in entry[1].flush(ts):
                    from_client = direction is not Direction.S2C
                    self._adu_segment(stream, from_client, item.raw, isinstance(item, Frame), ts)

    def _event_frames(self, event: Event, stream: Stream, conv: TcpConversation) -> list[bytes]:
        if event.kind is EventKind.CONNECT:
            return conv.open()
        if event.kind is EventKind.GAP:
            size = int(event.info.get("bytes", 0))
            if self._adu_segments and stream.transport is Transport.TCP:
                # one ADU per segment: numbered on, nothing for Wireshark to wait for
                direction = str(event.info.get("direction", Direction.C2S.value))
                self.losses.append((event.ts, stream, direction, size))
                client = direction != Direction.S2C.value
                side = "client" if client else "server"
                amount = "1 byte" if size == 1 else f"{size} bytes"
                self._loss_notes.setdefault((stream.id, client), []).append(
                    f"mbmon: {amount} of the {side}'s stream {'was' if size == 1 else 'were'} "
                    f"not captured before this segment (lost at {_utc_text(event.ts)})"
                )
                return []
            from_client = event.info.get("direction") == Direction.C2S.value
            if from_client:
                conv.client_next = (conv.client_next + size) & 0xFFFFFFFF
            else:
                conv.server_next = (conv.server_next + size) & 0xFFFFFFFF
            return [conv.ack(not from_client)]  # the peer had them: the gap shows
        if event.kind is EventKind.DISCONNECT:
            if event.info.get("how") == "idle":
                return []  # the dissector gave up on a quiet flow: nothing crossed the wire
            by_client = event.info.get("by") != "server"
            if event.info.get("how") == "rst":
                return [conv.reset(by_client)]
            if event.info.get("half_closed"):
                return [conv.segment(by_client, FIN | ACK)]
            return conv.close(by_client)
        return []

    def section_comments(self) -> list[str]:
        """What the export changed, for the pcapng section header (``shb_comment``):
        server ports rewritten and bytes lost where the segments are numbered on;
        the packets concerned carry a comment each."""
        out = [
            f"mbmon: Modbus/{transport.value.upper()} server port {port} in the original capture, "
            f"written as {new} (comment on each such stream's first packet)"
            for (transport, port), new in sorted(
                self.ports_rewritten.items(), key=lambda kv: (kv[0][0].value, kv[0][1])
            )
        ]
        if self.losses:
            lost = sum(n for _ts, _stream, _direction, n in self.losses)
            out.append(
                f"mbmon: {lost} byte(s) were not captured in {len(self.losses)} place(s); the "
                "segments are numbered contiguously, one ADU each (comment on the first "
                "segment after each loss)"
            )
        return out

    def flush(self) -> None:
        """Hand what was written so far to the OS (a live ``-w x.pcap`` on each tick);
        bytes an ADU framer holds wait for the rest of their ADU."""
        for writer in (self._pcapng, self._pcap, self._other):
            if writer is not None:
                writer.flush()

    def close(self) -> None:
        """Write what the framers hold, then finish the file(s); a capture that got
        nothing is still a valid (empty) one."""
        try:
            for stream, _ in list(self._framers.values()):
                self._flush_adus(stream, self._last_ts)
            for stream_id, decoder in list(self._bus_framers.items()):
                del self._bus_framers[stream_id]
                for frame in decoder.flush(self._last_ts):
                    self._emit(frame.ts, frame.raw, LINKTYPE_USER0, stream_id)
        finally:
            if self._pcapng is not None:
                self._pcapng.close()
                summary = self.section_comments()
                if summary and isinstance(self._out, str | Path):
                    PcapngWriter.comment_first_section(self._out, summary)
            elif self._pcap is not None:
                self._pcap.close()
            else:
                PcapWriter(self._out, LINKTYPE_ETHERNET, nanosecond=self._nanosecond).close()
            if self._other is not None:
                self._other.close()

    def __enter__(self) -> ChunkWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
