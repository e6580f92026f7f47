"""The dissector's general path, layer by layer: every link type it reads, IPv4 with
options and IPv6 with extension headers, TCP and UDP, whole or cut at any byte, or
damaged in one header field, lands in the counter that names what is wrong with it
(``Dissector.stats``) and never raises. The expected fate is worked out here from
how each packet was built, not from the dissector."""

from __future__ import annotations

import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.io.pcap import (
    LINKTYPE_ETHERNET,
    LINKTYPE_IPV4,
    LINKTYPE_IPV6,
    LINKTYPE_LINUX_SLL,
    LINKTYPE_LINUX_SLL2,
    LINKTYPE_LOOP,
    LINKTYPE_NULL,
    LINKTYPE_RAW,
    ipv4_packet,
    ipv6_packet,
    link_frame,
    tcp_header,
    udp_header,
)
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request
from mbmon.sources.dissect import CaptureConfig, Dissector

#: the counters of a packet's fate
FATES = ("modbus_packets", "non_modbus", "non_ip", "truncated", "fragments", "malformed",
         "unsupported_link")  # fmt: skip
#: link type -> its header length before the IP packet (VLAN tags come on top)
LINKS = {LINKTYPE_ETHERNET: 14, LINKTYPE_NULL: 4, LINKTYPE_LOOP: 4, LINKTYPE_RAW: 0, 12: 0,
         14: 0, LINKTYPE_LINUX_SLL: 16, LINKTYPE_LINUX_SLL2: 20, LINKTYPE_IPV4: 0,
         LINKTYPE_IPV6: 0}  # fmt: skip
#: IPv6 extension headers of 8 bytes each: hop-by-hop, routing, destination options,
#: a fragment header of a whole packet, an authentication header
EXTENSIONS = [(0, b""), (43, b"\x00\x00"), (60, b""), (44, b""), (51, b"\x00" * 6)]
V4, V6 = ("10.0.0.1", "10.0.0.2"), ("fd00::1", "fd00::2")


def _fates(frame: bytes, link: int) -> dict[str, int]:
    d = Dissector(CaptureConfig())
    out: list[Any] = []
    d.packet_general(1.0, link, 0, frame, 0, len(frame), out)
    d.packet(1.0, link, 0, frame, 0, len(frame), out)  # the fast path agrees
    stats = d.stats()
    return {k: stats[k] // 2 for k in FATES if stats[k]}


@st.composite
def packets(draw: Any) -> tuple[int, bytes, dict[str, int]]:
    """(link type, record, expected fates) of a Modbus or other packet, cut or whole."""
    v6 = draw(st.booleans())
    link = draw(st.sampled_from(sorted(LINKS)))
    if link in (LINKTYPE_IPV4, LINKTYPE_IPV6):
        link = LINKTYPE_IPV6 if v6 else LINKTYPE_IPV4
    src, dst = V6 if v6 else V4
    udp = draw(st.booleans())
    modbus = draw(st.booleans())
    dport = 502 if modbus else 8080
    payload = encode_adu(1, 1, encode_read_request(3, draw(st.integers(0, 99)), 2))
    if udp:
        segment = udp_header(src, dst, 40000, dport, payload)
    else:
        segment = tcp_header(src, dst, 40000, dport, 1000, 0, 0x18, payload)
    proto = 17 if udp else 6
    if v6:
        extensions = draw(st.lists(st.sampled_from(EXTENSIONS), max_size=3))
        ip = ipv6_packet(src, dst, proto, segment, extensions=extensions)
        ip_head, options = 40 + 8 * len(extensions), 0
    else:
        options = draw(st.sampled_from([0, 4, 8]))
        ip = ipv4_packet(src, dst, proto, segment, options=b"\x01" * options)
        ip_head = 20 + options
    vlans = draw(st.sampled_from([[], [(0x8100, 5)], [(0x88A8, 5), (0x8100, 6)]]))
    if link != LINKTYPE_ETHERNET:
        vlans = []
    frame = link_frame(link, ip, vlans=vlans)
    head = LINKS[link] + 4 * len(vlans)
    assert len(frame) == head + len(ip)
    cut = draw(st.sampled_from([len(frame), len(frame), draw(st.integers(0, len(frame)))]))
    transport = head + ip_head
    if cut == len(frame):
        fate = {"modbus_packets" if modbus else "non_modbus": 1}
    elif cut < head + (40 if v6 else 20) or (v6 and cut < transport):
        fate = {"truncated": 1}  # in the link, fixed IP or extension headers
    elif cut < transport:
        fate = {"malformed": 1}  # in IPv4 options: the header runs past its packet
    elif cut < transport + (8 if udp else 20):
        fate = {"truncated": 1}  # in the transport header
    elif modbus:
        fate = {"modbus_packets": 1, "truncated": 1}  # a Modbus packet, cut
    else:
        fate = {"non_modbus": 1}
    return link, frame[:cut], fate


@settings(max_examples=400, deadline=None)
@given(packets())
def test_every_layer_of_every_link_type_counts_what_is_wrong(
    packet: tuple[int, bytes, dict[str, int]],
) -> None:
    link, frame, fate = packet
    assert _fates(frame, link) == fate


def _ipv4(**kw: Any) -> bytes:
    return ipv4_packet(*V4, 6, tcp_header(*V4, 40000, 502, 1000, 0, 0x18, b"\x00" * 12), **kw)


def _field(data: bytes, at: int, value: int, fmt: str = "!B") -> bytes:
    return data[:at] + struct.pack(fmt, value) + data[at + struct.calcsize(fmt) :]


#: (case, link type, record, fates): one header field wrong at each layer (a packet to
#: a Modbus port counts as one before its transport header is checked)
DAMAGED = [
    ("unknown link type", 9999, _ipv4(), {"unsupported_link": 1}),
    ("interface never described", -1, _ipv4(), {"malformed": 1}),
    ("ARP on Ethernet", 1, link_frame(1, _ipv4())[:12] + b"\x08\x06" + _ipv4(), {"non_ip": 1}),
    ("IP version 5 on a raw link", 101, b"\x55" + _ipv4()[1:], {"non_ip": 1}),
    ("unknown loopback family", 0, b"\x07\x00\x00\x00" + _ipv4(), {"non_ip": 1}),
    ("loopback family in the other byte order", 0, b"\x00\x00\x00\x02" + _ipv4(),
     {"modbus_packets": 1}),
    ("a cut VLAN tag", 1, b"\x00" * 12 + b"\x81\x00\x00\x01\x08", {"truncated": 1}),
    ("IPv6 on the IPv4 link", 228, ipv6_packet(*V6, 6, b""), {"malformed": 1}),
    ("IPv4 header length under 20", 228, _field(_ipv4(), 0, 0x44), {"malformed": 1}),
    ("IPv4 total length under its header", 228, _field(_ipv4(), 2, 19, "!H"), {"malformed": 1}),
    ("IPv4 total length 0 (offload)", 228, _field(_ipv4(), 2, 0, "!H"), {"modbus_packets": 1}),
    ("IPv4 later fragment", 228, _ipv4(flags_fragment=0x0010), {"fragments": 1}),
    ("IPv4 first fragment", 228, _ipv4(flags_fragment=0x2000),
     {"fragments": 1, "modbus_packets": 1, "truncated": 1}),
    ("IPv6 version 4 in its header", 229, _field(ipv6_packet(*V6, 59, b""), 0, 0x40),
     {"malformed": 1}),
    ("IPv6 later fragment", 229, ipv6_packet(*V6, 6, b"", extensions=[(44, b"\x00\x08")]),
     {"fragments": 1}),
    ("IPv6 no next header", 229, ipv6_packet(*V6, 59, b"\x00" * 20), {"non_modbus": 1}),
    ("TCP data offset under 20", 228, _field(_ipv4(), 32, 0x40),
     {"modbus_packets": 1, "malformed": 1}),
    ("TCP data offset past the packet", 228, _field(_ipv4(), 32, 0xF0),
     {"modbus_packets": 1, "truncated": 1}),
    ("UDP length under 8", 228, ipv4_packet(*V4, 17, _field(udp_header(*V4, 1, 502, b"ab"), 4, 7,
     "!H")), {"modbus_packets": 1, "malformed": 1}),
    ("UDP length past the packet", 228, ipv4_packet(*V4, 17, _field(udp_header(*V4, 1, 502), 4, 9,
     "!H")), {"modbus_packets": 1, "truncated": 1}),
]  # fmt: skip


@pytest.mark.parametrize(("case", "link", "frame", "fate"), DAMAGED, ids=[d[0] for d in DAMAGED])
def test_a_wrong_header_field_is_counted_where_it_is(
    case: str, link: int, frame: bytes, fate: dict[str, int]
) -> None:
    assert _fates(frame, link) == fate, case
