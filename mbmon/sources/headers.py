"""The link layer and IP headers of one captured record, for the dissector's general
path (:meth:`mbmon.sources.dissect.Dissector.packet_general`): every link type the
reader knows, VLAN tags, IPv4 with options and fragments, IPv6 with extension
headers. Each function reads one layer and says where the next one starts, or
counts what is wrong with its header in ``counts`` (the dissector's own counters,
:class:`HeaderCounts`) and gives ``None``: bytes never raise.
"""

from __future__ import annotations

import struct
from typing import Protocol


class HeaderCounts(Protocol):
    """The counters a header that makes no sense is counted in (the dissector's)."""

    truncated: int
    malformed: int
    fragments: int
    unsupported_link: int


_RAW = frozenset({101, 12, 14})
_LOOPBACK = frozenset({0, 108})
_AF_INET6 = frozenset({10, 23, 24, 28, 30})
_VLAN = frozenset({0x8100, 0x88A8, 0x9100})
_IPV6_EXT = frozenset({0, 43, 60, 135, 139, 140, 253, 254})

_ipv4_unpack = struct.Struct("!BxHxxHxB").unpack_from
_h_unpack = struct.Struct("!H").unpack_from
_af_unpack = struct.Struct("<I").unpack_from
#: link types with a fixed header: (header length, where its ethertype is)
_LINK_HEADERS = {1: (14, 12), 113: (16, 14), 276: (20, 0)}  # Ethernet, Linux cooked v1, v2
#: link types that are IP packets of one version: their ethertype
_IP_LINKS = {228: 0x0800, 229: 0x86DD}
#: an IP header's meaning for the transport: (protocol, where its header starts, where
#: the IP packet ends in the record, source + destination addresses, the packet is cut)
Ip = tuple[int, int, int, bytes, bool]


def link_layer(
    counts: HeaderCounts, link: int, buf: bytes, off: int, end: int
) -> tuple[int, int] | None:
    """The link layer of one record: (ethertype, where the network layer starts)
    after any VLAN tags, or ``None`` (counted) when it is cut, unknown or not IP."""
    header = _LINK_HEADERS.get(link)
    if header is not None:
        size, at = header
        if end - off < size:
            counts.truncated += 1
            return None
        et = (buf[off + at] << 8) | buf[off + at + 1]
        off += size
    elif link in _RAW:
        if end <= off:
            counts.truncated += 1
            return None
        version = buf[off] >> 4
        et = 0x0800 if version == 4 else 0x86DD if version == 6 else 0
    elif link in _LOOPBACK:
        if end - off < 4:
            counts.truncated += 1
            return None
        family = _af_unpack(buf, off)[0]
        if family > 0xFFFF:  # written in the other byte order
            family = int.from_bytes(buf[off : off + 4], "big")
        et = 0x0800 if family == 2 else 0x86DD if family in _AF_INET6 else 0
        off += 4
    elif link in _IP_LINKS:
        et = _IP_LINKS[link]
    elif link < 0:  # a packet block naming an interface that was never described
        counts.malformed += 1
        return None
    else:
        counts.unsupported_link += 1
        return None
    while et in _VLAN:
        if end - off < 4:
            counts.truncated += 1
            return None
        et = (buf[off + 2] << 8) | buf[off + 3]
        off += 4
    return et, off


def ipv4_header(counts: HeaderCounts, buf: bytes, off: int, end: int) -> Ip | None:
    """An IPv4 header at ``off`` (options, fragments, a length the capture left
    out): what follows it, or ``None`` (counted)."""
    if end - off < 20:
        counts.truncated += 1
        return None
    vihl, total, frag, proto = _ipv4_unpack(buf, off)
    ihl = (vihl & 15) << 2
    if vihl >> 4 != 4 or ihl < 20:
        counts.malformed += 1
        return None
    short = False
    if total == 0:  # segmentation offload: the length is left to the capture
        ip_end = end
    elif total < ihl:
        counts.malformed += 1
        return None
    else:
        ip_end = off + total
        if ip_end > end:  # cut by the snap length: counted if it matters below
            short = True
            ip_end = end
    if frag & 0x3FFF:  # more-fragments or an offset
        counts.fragments += 1
        if frag & 0x1FFF:  # not the first fragment: no transport header
            return None
        short = True  # the first one: a cut packet
    return proto, off + ihl, ip_end, buf[off + 12 : off + 20], short


def ipv6_header(counts: HeaderCounts, buf: bytes, off: int, end: int) -> Ip | None:
    """An IPv6 header at ``off`` and its extension headers: what follows them, or
    ``None`` (counted)."""
    if end - off < 40:
        counts.truncated += 1
        return None
    if buf[off] >> 4 != 6:
        counts.malformed += 1
        return None
    plen = (buf[off + 4] << 8) | buf[off + 5]
    ip_end = off + 40 + plen if plen else end
    short = ip_end > end
    if short:
        ip_end = end
    after = _ipv6_extensions(counts, buf, buf[off + 6], off + 40, ip_end)
    if after is None:
        return None
    proto, l4, fragment = after
    return proto, l4, ip_end, buf[off + 8 : off + 40], short or fragment


def _ipv6_extensions(
    counts: HeaderCounts, buf: bytes, proto: int, l4: int, ip_end: int
) -> tuple[int, int, bool] | None:
    """Walk up to 16 IPv6 extension headers from ``l4``: (transport protocol, where
    it starts, a first fragment), or ``None`` (counted: cut, or a later fragment)."""
    fragment = False
    for _ in range(16):
        if proto in _IPV6_EXT or proto == 44 or proto == 51:
            if ip_end - l4 < 8:
                counts.truncated += 1
                return None
        if proto in _IPV6_EXT:
            proto, l4 = buf[l4], l4 + ((buf[l4 + 1] + 1) << 3)
        elif proto == 44:  # fragment header
            frag = _h_unpack(buf, l4 + 2)[0]
            if frag & 0xFFF9:  # offset or more-fragments
                counts.fragments += 1
                if frag & 0xFFF8:  # not the first fragment
                    return None
                fragment = True
            proto, l4 = buf[l4], l4 + 8
        elif proto == 51:  # authentication header
            proto, l4 = buf[l4], l4 + ((buf[l4 + 1] + 2) << 2)
        else:
            break
    return proto, l4, fragment
