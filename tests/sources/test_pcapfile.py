"""Capture files to chunks and events: containers, link types, streams, damage."""

from __future__ import annotations

import gzip
import os
import struct
import threading
from collections.abc import Sequence
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mbmon.io import pcap as pw
from mbmon.io.pcap import PcapngWriter, PcapWriter, TcpConversation
from mbmon.model import Chunk, Direction, Event, EventKind, Transport
from mbmon.sources.pcapfile import CaptureConfig, CaptureError, read_capture

T0 = 1_700_000_000.0
CLIENT = "192.168.1.10:40001"
SERVER = "192.168.1.2:502"
REQUEST = bytes.fromhex("000100000006010300000002")  # read 2 holding registers
RESPONSE = bytes.fromhex("00010000000701030400070008")


def write_pcap(path: Path, frames: Sequence[bytes], linktype: int = 1, **kw: bool) -> Path:
    with PcapWriter(path, linktype, **kw) as writer:
        for i, frame in enumerate(frames):
            writer.write(T0 + i / 100, frame)
    return path


def exchange(conv: TcpConversation, rounds: int = 1) -> list[bytes]:
    """Handshake, ``rounds`` request/response pairs, orderly close by the client."""
    frames = conv.open()
    for _ in range(rounds):
        frames += [conv.send(True, REQUEST), conv.send(False, RESPONSE)]
    return frames + conv.close(True)


DEFAULT = CaptureConfig()


def read_all(path: Path, config: CaptureConfig = DEFAULT, **kw: object) -> list[Chunk | Event]:
    return list(read_capture(path, config, **kw))  # type: ignore[arg-type]


def chunks(items: Sequence[Chunk | Event]) -> list[Chunk]:
    return [i for i in items if isinstance(i, Chunk)]


def events(items: Sequence[Chunk | Event], kind: EventKind | None = None) -> list[Event]:
    return [i for i in items if isinstance(i, Event) and (kind is None or i.kind is kind)]


def summary(items: Sequence[Chunk | Event]) -> list[tuple[object, ...]]:
    out: list[tuple[object, ...]] = []
    for i in items:
        if isinstance(i, Chunk):
            out.append((i.stream.id, i.direction.value, i.data))
        else:
            out.append((i.stream.id if i.stream else None, i.kind.value))
    return out


EXPECTED_EXCHANGE = [
    (0, "connect"),
    (0, "c2s", REQUEST),
    (0, "s2c", RESPONSE),
    (0, "disconnect"),
]


# ----------------------------------------------------------------- containers


@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("nanosecond", [False, True])
def test_pcap_in_both_byte_orders_and_resolutions(
    tmp_path: Path, big_endian: bool, nanosecond: bool
) -> None:
    path = tmp_path / "x.pcap"
    with PcapWriter(path, 1, big_endian=big_endian, nanosecond=nanosecond) as writer:
        for i, frame in enumerate(exchange(TcpConversation(CLIENT, SERVER))):
            writer.write(T0 + i * 0.25 + 0.000123, frame)
    items = read_all(path)
    assert summary(items) == EXPECTED_EXCHANGE
    request = chunks(items)[0]
    assert request.ts == pytest.approx(T0 + 3 * 0.25 + 0.000123, abs=1e-6)
    assert request.stream.client == CLIENT
    assert request.stream.server == SERVER
    assert request.stream.transport is Transport.TCP


@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("tsresol", [None, 9, 3, 0x80 | 20])
def test_pcapng_byte_orders_and_timestamp_resolutions(
    tmp_path: Path, big_endian: bool, tsresol: int | None
) -> None:
    path = tmp_path / "x.pcapng"
    with PcapngWriter(path, big_endian=big_endian) as writer:
        writer.add_interface(1, tsresol=tsresol)
        for i, frame in enumerate(exchange(TcpConversation(CLIENT, SERVER))):
            writer.write(T0 + i * 0.5, frame)
    items = read_all(path)
    assert summary(items) == EXPECTED_EXCHANGE
    precision = {None: 1e-6, 9: 1e-6, 3: 1e-3, 0x80 | 20: 1e-6}[tsresol]
    assert chunks(items)[1].ts == pytest.approx(T0 + 4 * 0.5, abs=precision)


def test_pcapng_tsoffset_is_added(tmp_path: Path) -> None:
    path = tmp_path / "x.pcapng"
    with PcapngWriter(path) as writer:
        writer.add_interface(1, tsoffset=1_000_000)
        for frame in exchange(TcpConversation(CLIENT, SERVER)):
            writer.write(T0, frame, tsoffset=1_000_000)
    assert chunks(read_all(path))[0].ts == pytest.approx(T0, abs=1e-6)


def test_pcapng_simple_obsolete_and_unknown_blocks(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    frames = exchange(conv)
    path = tmp_path / "x.pcapng"
    with PcapngWriter(path) as writer:
        writer.add_interface(1)
        writer.write_block(4, b"\0\0\0\0")  # name resolution block (empty)
        writer.write_block(0x0BAD, b"custom")  # unknown: skipped
        for frame in frames[:3]:
            writer.write_obsolete(T0, frame)
        writer.write_simple(frames[3])  # no timestamp: takes the previous one
        writer.write_block(5, bytes(12))  # interface statistics block
        for frame in frames[4:]:
            writer.write(T0 + 1, frame)
    items = read_all(path)
    assert summary(items) == EXPECTED_EXCHANGE
    assert chunks(items)[0].ts == pytest.approx(T0)


def test_pcapng_interfaces_with_different_link_types_and_a_new_section(tmp_path: Path) -> None:
    eth = TcpConversation(CLIENT, SERVER)
    raw = TcpConversation("10.9.9.9:40002", "10.9.9.1:502", linktype=pw.LINKTYPE_RAW)
    path = tmp_path / "multi.pcapng"
    with PcapngWriter(path) as writer:
        if_eth = writer.add_interface(pw.LINKTYPE_ETHERNET)
        if_raw = writer.add_interface(pw.LINKTYPE_RAW, tsresol=9)
        if_bus = writer.add_interface(pw.LINKTYPE_USER0)
        for frame in eth.open():
            writer.write(T0, frame, interface=if_eth)
        for frame in raw.open():
            writer.write(T0 + 1, frame, interface=if_raw)
        writer.write(T0 + 2, eth.send(True, REQUEST), interface=if_eth)
        writer.write(T0 + 3, raw.send(True, b"\x00\x05" + REQUEST[2:]), interface=if_raw)
        writer.write(T0 + 4, b"\x01\x03\x00\x00\x00\x01\x84\x0a", interface=if_bus)
        # a second section in the other byte order: interfaces are described anew
        writer.new_section(big_endian=True)
        writer.add_interface(pw.LINKTYPE_RAW)
        writer.write(T0 + 5, raw.send(False, RESPONSE), interface=0)
    items = read_all(path)
    assert summary(items) == [
        (0, "connect"),
        (1, "connect"),
        (0, "c2s", REQUEST),
        (1, "c2s", b"\x00\x05" + REQUEST[2:]),
        (2, "bus", b"\x01\x03\x00\x00\x00\x01\x84\x0a"),
        (1, "s2c", RESPONSE),
    ]
    assert chunks(items)[2].stream.transport is Transport.RTU


def test_gzip_compressed_capture(tmp_path: Path) -> None:
    plain = write_pcap(tmp_path / "x.pcap", exchange(TcpConversation(CLIENT, SERVER)))
    packed = tmp_path / "x.pcap.gz"
    packed.write_bytes(gzip.compress(plain.read_bytes()))
    assert summary(read_all(packed)) == EXPECTED_EXCHANGE


def _5view(path: Path, records: Sequence[tuple[int, bytes]], file_type: int = 0x18001000) -> Path:
    """An InfoVista 5View file as wireshark's wiretap/5views.c lays it out."""
    header = struct.pack("<IIIII12x", 0xAAAAAAAA, 32, 0x00010000, 24, file_type)
    header += struct.pack("<IHHI", 0x80000007, 4, 1, 0) + struct.pack("<IHHI", 0x20000000, 4, 1, 0)
    body = b""
    for i, (subtype, data) in enumerate(records):
        body += struct.pack(
            "<IHHIIIIIII", 0x3333EEEE, 36, 0x4000, 0x80000000, subtype, len(data), 1, 1000 + i, 5, 0
        )
        body += data
    path.write_bytes(header + body)
    return path


def test_5view_frames_are_read_and_other_records_skipped(tmp_path: Path) -> None:
    frames = exchange(TcpConversation(CLIENT, SERVER))
    records = [(0, f) for f in frames]
    records.insert(4, (7, b"an alarm record"))
    items = read_all(_5view(tmp_path / "x.5vw", records))
    assert summary(items) == EXPECTED_EXCHANGE
    assert chunks(items)[0].ts == pytest.approx(1003 + 5e-9)


def test_5view_of_a_wan_capture_names_the_format_and_the_fix(tmp_path: Path) -> None:
    path = _5view(tmp_path / "x.5vw", [], file_type=0x18002000)
    with pytest.raises(CaptureError, match=r"5View.*editcap -F pcap"):
        read_capture(path)


# ----------------------------------------------------------------- link types


@pytest.mark.parametrize(
    "linktype",
    [0, 1, 12, 14, 101, 108, 113, 228, 276],
    ids=["null", "ether", "raw12", "raw14", "raw", "loop", "sll", "ipv4", "sll2"],
)
def test_every_ipv4_link_type(tmp_path: Path, linktype: int) -> None:
    conv = TcpConversation(CLIENT, SERVER, linktype=linktype)
    path = write_pcap(tmp_path / "x.pcap", exchange(conv), linktype)
    assert summary(read_all(path)) == EXPECTED_EXCHANGE


@pytest.mark.parametrize("linktype", [0, 1, 101, 108, 113, 229, 276])
def test_every_ipv6_link_type(tmp_path: Path, linktype: int) -> None:
    conv = TcpConversation("[2001:db8::10]:40001", "[2001:db8::2]:502", linktype=linktype)
    items = read_all(write_pcap(tmp_path / "x.pcap", exchange(conv), linktype))
    assert summary(items) == EXPECTED_EXCHANGE
    assert chunks(items)[0].stream.client == "[2001:db8::10]:40001"
    assert chunks(items)[0].stream.server == "[2001:db8::2]:502"


def test_null_link_in_big_endian_byte_order(tmp_path: Path) -> None:
    ip = pw.ip_packet(
        "10.0.0.1", "10.0.0.2", 17, pw.udp_header("10.0.0.1", "10.0.0.2", 9, 502, b"x")
    )
    frame = pw.link_frame(0, ip, null_big_endian=True)
    assert frame[:4] == b"\0\0\0\x02"
    assert [c.data for c in chunks(read_all(write_pcap(tmp_path / "x.pcap", [frame], 0)))] == [b"x"]


@pytest.mark.parametrize(
    "vlans", [[(0x8100, 10)], [(0x88A8, 100), (0x8100, 10)], [(0x9100, 5), (0x8100, 6)]]
)
def test_vlan_tags_are_skipped(tmp_path: Path, vlans: list[tuple[int, int]]) -> None:
    conv = TcpConversation(CLIENT, SERVER, vlans=vlans)
    assert summary(read_all(write_pcap(tmp_path / "x.pcap", exchange(conv)))) == EXPECTED_EXCHANGE


def test_ethernet_padding_is_not_payload(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    frames = conv.open()
    small = conv.send(True, b"\x00\x01")  # 56 bytes: a wire frame is padded to 60
    frames.append(small + b"\xee" * (60 - len(small)))
    assert [c.data for c in chunks(read_all(write_pcap(tmp_path / "x.pcap", frames)))] == [
        b"\x00\x01"
    ]


def test_ipv4_options_and_ipv6_extension_headers(tmp_path: Path) -> None:
    seg = pw.tcp_header("10.0.0.1", "10.0.0.2", 40000, 502, 1, 0, 0x18, b"v4")
    v4 = pw.ipv4_packet("10.0.0.1", "10.0.0.2", 6, seg, options=b"\x01\x01\x01\x00")  # NOPs + EOL
    seg6 = pw.tcp_header("::1", "::2", 40000, 502, 1, 0, 0x18, b"v6")
    v6 = pw.ipv6_packet(
        "::1",
        "::2",
        6,
        seg6,
        extensions=[(0, b"\x01\x04\0\0\0\0"), (60, b""), (44, b"\0\0\0\0\0\x07"), (51, bytes(10))],
    )
    frames = [pw.link_frame(1, v4), pw.link_frame(1, v6)]
    items = read_all(write_pcap(tmp_path / "x.pcap", frames))
    assert [(c.stream.client, c.data) for c in chunks(items)] == [
        ("10.0.0.1:40000", b"v4"),
        ("[::1]:40000", b"v6"),
    ]


def test_fragments_are_counted_and_only_first_tcp_fragments_read(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    frames = conv.open()
    segment = pw.tcp_header(
        "192.168.1.10", "192.168.1.2", 40001, 502, conv.client_next, conv.server_next, 0x18, REQUEST
    )
    # first fragment: TCP header + 4 payload bytes; second: the other 8 bytes
    frames.append(
        pw.link_frame(
            1, pw.ipv4_packet("192.168.1.10", "192.168.1.2", 6, segment[:24], flags_fragment=0x2000)
        )
    )
    frames.append(
        pw.link_frame(
            1, pw.ipv4_packet("192.168.1.10", "192.168.1.2", 6, segment[24:], flags_fragment=3)
        )
    )
    conv.client_next += len(REQUEST)
    frames.append(conv.send(False, RESPONSE))  # acknowledges the whole request
    udp = pw.udp_header("10.0.0.1", "10.0.0.2", 5000, 502, bytes(20))
    frames.append(
        pw.link_frame(
            1, pw.ipv4_packet("10.0.0.1", "10.0.0.2", 17, udp[:16], flags_fragment=0x2000)
        )
    )
    v6 = pw.ipv6_packet("::1", "::2", 17, udp[:16], extensions=[(44, b"\0\x01\0\0\0\x07")])  # M=1
    v6_later = pw.ipv6_packet("::1", "::2", 17, udp[16:], extensions=[(44, b"\0\x10\0\0\0\x07")])
    frames += [pw.link_frame(1, v6), pw.link_frame(1, v6_later)]
    stats: dict[str, int] = {}
    items = read_all(write_pcap(tmp_path / "x.pcap", frames), stats=stats)
    assert summary(items) == [
        (0, "connect"),
        (0, "c2s", REQUEST[:4]),
        (0, "gap"),  # revealed by the response's acknowledgement, so before it
        (0, "s2c", RESPONSE),
    ]
    assert stats["fragments"] == 5


def test_udp_datagrams_are_chunks_each(tmp_path: Path) -> None:
    frames = [
        pw.udp_frame(1, "10.0.0.5", "10.0.0.6", 50000, 502, REQUEST),
        pw.udp_frame(1, "10.0.0.6", "10.0.0.5", 502, 50000, RESPONSE),
        pw.udp_frame(1, "10.0.0.6", "10.0.0.5", 502, 50000, b""),  # empty: nothing
        pw.udp_frame(1, "10.0.0.5", "10.0.0.6", 50000, 502, REQUEST),
    ]
    items = read_all(write_pcap(tmp_path / "x.pcap", frames))
    assert summary(items) == [(0, "c2s", REQUEST), (0, "s2c", RESPONSE), (0, "c2s", REQUEST)]
    stream = chunks(items)[0].stream
    assert (stream.transport, stream.client, stream.server) == (
        Transport.UDP,
        "10.0.0.5:50000",
        "10.0.0.6:502",
    )


def test_rtu_over_tcp_and_udp_ports(tmp_path: Path) -> None:
    rtu = bytes.fromhex("010300000002c40b")
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:4001")
    frames = [*conv.open(), conv.send(True, rtu)]
    frames.append(pw.udp_frame(1, "10.0.0.1", "10.0.0.2", 40000, 4002, rtu))
    frames.append(pw.udp_frame(1, "10.0.0.1", "10.0.0.2", 40000, 502, rtu))
    config = CaptureConfig(tcp_ports=frozenset({502}), rtu_ports=frozenset({4001, 4002}))
    transports = [
        c.stream.transport
        for c in chunks(read_all(write_pcap(tmp_path / "x.pcap", frames), config))
    ]
    assert transports == [Transport.RTU_OVER_TCP, Transport.RTU_OVER_UDP, Transport.UDP]


def test_a_port_in_both_sets_is_rtu(tmp_path: Path) -> None:
    frames = [pw.udp_frame(1, "10.0.0.1", "10.0.0.2", 40000, 502, b"\x01")]
    config = CaptureConfig(rtu_ports=frozenset({502}))
    items = read_all(write_pcap(tmp_path / "x.pcap", frames), config)
    assert chunks(items)[0].stream.transport is Transport.RTU_OVER_UDP


def test_link_type_147_is_an_rtu_bus(tmp_path: Path) -> None:
    records = [bytes.fromhex("0103"), bytes.fromhex("00000002c40b"), b"", bytes.fromhex("01")]
    path = write_pcap(tmp_path / "bus.pcap", records, pw.LINKTYPE_USER0)
    items = read_all(path)
    assert [c.data for c in chunks(items)] == [r for r in records if r]
    stream = chunks(items)[0].stream
    assert stream.transport is Transport.RTU
    assert stream.client == stream.server == "bus.pcap"
    assert {c.direction for c in chunks(items)} == {Direction.BUS}
    assert chunks(items)[1].ts == pytest.approx(T0 + 0.01)


def test_non_modbus_traffic_is_counted_not_yielded(tmp_path: Path) -> None:
    http = TcpConversation("10.0.0.1:40000", "10.0.0.2:80")
    arp = pw.ethernet_frame(bytes(28), 0x0806)
    icmp = pw.link_frame(1, pw.ipv4_packet("10.0.0.1", "10.0.0.2", 1, bytes(8)))
    stats: dict[str, int] = {}
    frames = [*exchange(http), arp, icmp]
    assert read_all(write_pcap(tmp_path / "x.pcap", frames), stats=stats) == []
    assert stats["packets"] == len(frames)
    assert stats["non_modbus"] == len(frames) - 1
    assert stats["non_ip"] == 1
    assert stats["modbus_packets"] == 0


def test_unknown_link_type_is_counted(tmp_path: Path) -> None:
    stats: dict[str, int] = {}
    assert read_all(write_pcap(tmp_path / "x.pcap", [b"abc"], 105), stats=stats) == []
    assert stats["unsupported_link"] == 1


# ----------------------------------------------------------------- streams


def test_server_is_the_configured_port_whatever_sends_first(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    conv.open()  # not captured: the capture starts mid-connection with a response
    frames = [conv.send(False, RESPONSE), conv.send(True, REQUEST)]
    items = read_all(write_pcap(tmp_path / "x.pcap", frames))
    assert summary(items) == [(0, "s2c", RESPONSE), (0, "c2s", REQUEST)]
    assert (chunks(items)[0].stream.client, chunks(items)[0].stream.server) == (CLIENT, SERVER)


def test_both_ports_configured_syn_receiver_is_server(tmp_path: Path) -> None:
    conv = TcpConversation("10.0.0.1:502", "10.0.0.2:1502")
    items = read_all(
        write_pcap(tmp_path / "x.pcap", exchange(conv)),
        CaptureConfig(tcp_ports=frozenset({502, 1502})),
    )
    assert chunks(items)[0].stream.server == "10.0.0.2:1502"
    assert chunks(items)[0].direction is Direction.C2S


def test_both_ports_configured_mid_stream_lower_port_is_server(tmp_path: Path) -> None:
    conv = TcpConversation("10.0.0.1:1502", "10.0.0.2:502")
    conv.open()
    frames = [conv.send(False, RESPONSE)]
    config = CaptureConfig(tcp_ports=frozenset({502, 1502}))
    items = read_all(write_pcap(tmp_path / "x.pcap", frames), config)
    assert chunks(items)[0].stream.server == "10.0.0.2:502"
    assert chunks(items)[0].direction is Direction.S2C


def test_stream_ids_in_order_of_first_appearance_and_reused_addresses(tmp_path: Path) -> None:
    a = TcpConversation(CLIENT, SERVER)
    b = TcpConversation("192.168.1.11:40001", SERVER)
    frames = [*a.open(), pw.udp_frame(1, "10.0.0.5", "10.0.0.6", 50000, 502, b"u"), *b.open()]
    frames += [a.send(True, b"a1"), b.send(True, b"b1")]
    frames += a.close(True)
    # same 4-tuple again after the FINs: a new connection
    a2 = TcpConversation(CLIENT, SERVER, client_isn=90000)
    frames += [*a2.open(), a2.send(True, b"a2"), a2.reset(False)]
    # and again after the RST
    a3 = TcpConversation(CLIENT, SERVER, client_isn=190000)
    frames += [*a3.open(), a3.send(True, b"a3")]
    # a new SYN with another ISN while b is still open replaces b
    b2 = TcpConversation("192.168.1.11:40001", SERVER, client_isn=7)
    frames += [*b2.open(), b2.send(True, b"b2")]
    items = read_all(write_pcap(tmp_path / "x.pcap", frames))
    assert summary(items) == [
        (0, "connect"),
        (1, "c2s", b"u"),
        (2, "connect"),
        (0, "c2s", b"a1"),
        (2, "c2s", b"b1"),
        (0, "disconnect"),
        (3, "connect"),
        (3, "c2s", b"a2"),
        (3, "disconnect"),
        (4, "connect"),
        (4, "c2s", b"a3"),
        (5, "connect"),
        (5, "c2s", b"b2"),
    ]
    assert [e.info for e in events(items, EventKind.DISCONNECT)] == [
        {"how": "fin", "by": "client"},
        {"how": "rst", "by": "server"},
    ]


def test_reused_addresses_without_a_captured_handshake(tmp_path: Path) -> None:
    old = TcpConversation(CLIENT, SERVER)
    frames = [*old.open(), old.send(True, b"old"), *old.close(True)]
    frames.append(old.segment(True, pw.PSH | pw.ACK, b"old", seq=old.client_isn + 1))  # straggler
    new = TcpConversation(CLIENT, SERVER, client_isn=0x40000000, server_isn=0x50000000)
    new.open()  # not captured
    frames += [new.send(True, b"new"), new.reset(True)]
    newer = TcpConversation(CLIENT, SERVER, client_isn=0x60000000, server_isn=0x70000000)
    _syn, syn_ack, ack = newer.open()  # the SYN is not captured
    frames += [syn_ack, ack, newer.send(True, b"newer")]
    stats: dict[str, int] = {}
    items = read_all(write_pcap(tmp_path / "x.pcap", frames), stats=stats)
    assert summary(items) == [
        (0, "connect"),
        (0, "c2s", b"old"),
        (0, "disconnect"),
        (1, "c2s", b"new"),
        (1, "disconnect"),
        (2, "connect"),
        (2, "c2s", b"newer"),
    ]
    assert stats["after_close"] == 1


def test_reassembly_through_a_file_retransmission_reorder_and_gap(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    frames = conv.open()
    first = conv.send(True, b"AAAA")
    second = conv.send(True, b"BBBB")
    third = conv.send(True, b"CCCC")
    conv.send(True, b"DDDD")  # lost by the capture
    fifth = conv.send(True, b"EEEE")
    frames += [first, first, third, second, fifth, conv.ack(False), conv.send(False, b"ok")]
    stats: dict[str, int] = {}
    items = read_all(write_pcap(tmp_path / "x.pcap", frames), stats=stats)
    assert summary(items) == [
        (0, "connect"),
        (0, "c2s", b"AAAA"),
        (0, "c2s", b"BBBB"),
        (0, "c2s", b"CCCC"),
        (0, "gap"),
        (0, "c2s", b"EEEE"),
        (0, "s2c", b"ok"),
    ]
    assert events(items, EventKind.GAP)[0].info == {
        "direction": "c2s",
        "bytes": 4,
        "reason": "acked-unseen",
    }
    assert stats["retransmissions"] == 1
    assert stats["out_of_order"] == 2
    assert stats["gaps"] == 1
    assert stats["gap_bytes"] == 4


def test_half_closed_at_end_of_capture(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    frames = [*conv.open(), conv.segment(True, pw.FIN | pw.ACK)]
    items = read_all(write_pcap(tmp_path / "x.pcap", frames))
    assert events(items, EventKind.DISCONNECT)[0].info == {
        "how": "fin",
        "by": "client",
        "half_closed": True,
    }


# ----------------------------------------------------------------- bad input


def test_missing_file_raises(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match=r"nope\.pcap: cannot open"):
        read_capture(tmp_path / "nope.pcap")


def test_directory_raises(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="cannot open"):
        read_capture(tmp_path)


def test_html_file_is_not_a_capture(tmp_path: Path) -> None:
    path = tmp_path / "capture.pcap"
    path.write_bytes(b"<!DOCTYPE html><html></html>")
    with pytest.raises(CaptureError) as info:
        read_capture(path)
    assert str(info.value) == f"{path}: not a pcap or pcapng file (magic 0x3c21444f)"


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "empty file"),
        (b"\xd4\xc3", "too short"),
        (b"\xd4\xc3\xb2\xa1\x02\x00", "truncated pcap file header"),
        (struct.pack("<IHHiIII", 0xA1B2C3D4, 9, 4, 0, 0, 65535, 1), "unsupported pcap version 9"),
        (b"\x0a\x0d\x0d\x0a\x1c\x00\x00\x00\x00\x00\x00\x00", "corrupt pcapng section header"),
    ],
)
def test_broken_file_headers_raise(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "x.pcap"
    path.write_bytes(content)
    with pytest.raises(CaptureError, match=message):
        read_capture(path)


def _record_ends(data: bytes, first: int) -> set[int]:
    """Offsets where pcap records end (a cut there leaves a valid, shorter file)."""
    ends = {first}
    pos = first
    while pos < len(data):
        caplen = struct.unpack_from("<I", data, pos + 8)[0]
        pos += 16 + caplen
        ends.add(pos)
    return ends


def test_truncated_pcap_at_every_offset(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    full = write_pcap(tmp_path / "full.pcap", exchange(conv, rounds=3)).read_bytes()
    whole = read_all(tmp_path / "full.pcap")
    ends = _record_ends(full, 24)
    cut_path = tmp_path / "capture.pcap"
    for cut in range(24, len(full)):
        cut_path.write_bytes(full[:cut])
        items = read_all(cut_path)
        errors = events(items, EventKind.ERROR)
        if cut in ends:
            assert errors == []
            body = items
        else:
            assert len(errors) == 1 and items[-1] is errors[0]
            body = items[:-1]
            complete = sum(1 for e in ends if e <= cut) - 1  # records before the cut
            start = max(e for e in ends if e <= cut)
            assert errors[0].stream is None
            assert errors[0].info["message"] == (
                f"{cut_path}: truncated record{' header' if cut - start < 16 else ''} "
                f"at byte {start} (packet {complete + 1}); {complete} packets read"
            )
        # every chunk before the cut comes out, in order (a half-closed connection
        # may end with its DISCONNECT instead of the final FIN exchange)
        got = [i for i in summary(body) if i[1] != "disconnect"]
        want = [i for i in summary(whole) if i[1] != "disconnect"]
        assert got == want[: len(got)]
        sent = sum(1 for e in ends if e <= cut) - 1
        expected_chunks = sum(1 for f in range(sent) if f in (3, 4, 5, 6, 7, 8))
        assert len(chunks(body)) == expected_chunks


@pytest.mark.parametrize(
    "tail",
    [
        pytest.param(bytes(40), id="zero-filled"),  # the file was never written to the end
        # a record whose length field was garbled: its "time" and bytes are noise
        pytest.param(struct.pack("<IIII", 4_000_000_000, 7, 20, 20) + b"\xff" * 12, id="garbled"),
    ],
)
def test_error_after_damage_carries_the_last_good_time(tmp_path: Path, tail: bytes) -> None:
    """The ERROR event (and what the end releases) is stamped with
    the time of the last record that made sense, not with a damaged record's."""
    conv = TcpConversation(CLIENT, SERVER)
    path = write_pcap(tmp_path / "x.pcap", [*conv.open(), conv.send(True, REQUEST)])
    path.write_bytes(path.read_bytes() + tail)
    items = read_all(path)
    (error,) = events(items, EventKind.ERROR)
    assert "truncated record" in error.info["message"]
    assert error.ts == T0 + 3 / 100  # the request's record
    assert max(i.ts for i in items) == T0 + 3 / 100


def test_truncated_pcapng_at_every_offset(tmp_path: Path) -> None:
    path = tmp_path / "full.pcapng"
    with PcapngWriter(path) as writer:
        writer.add_interface(1)
        for frame in exchange(TcpConversation(CLIENT, SERVER)):
            writer.write(T0, frame)
    full = path.read_bytes()
    want = [i for i in summary(read_all(path)) if i[1] != "disconnect"]
    cut_path = tmp_path / "cut.pcapng"
    for cut in range(28, len(full)):  # 28: the section header block is whole
        cut_path.write_bytes(full[:cut])
        items = read_all(cut_path)
        got = [i for i in summary(items) if i[1] not in ("disconnect", "error")]
        assert got == want[: len(got)]
        assert len(events(items, EventKind.ERROR)) <= 1
        assert all(not isinstance(i, Event) or i.kind is not EventKind.ERROR for i in items[:-1])


def test_corrupt_pcapng_block_length_stops_with_an_error(tmp_path: Path) -> None:
    path = tmp_path / "x.pcapng"
    with PcapngWriter(path) as writer:
        writer.add_interface(1)
        conv = TcpConversation(CLIENT, SERVER)
        for frame in conv.open():
            writer.write(T0, frame)
        writer.write(T0, conv.send(True, REQUEST))
        offset = writer._f.tell()
        writer.write(T0, conv.send(False, RESPONSE))
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, offset + 4, 13)  # not a multiple of 4
    path.write_bytes(bytes(data))
    items = read_all(path)
    assert summary(items)[:-1] == [(0, "connect"), (0, "c2s", REQUEST)]
    assert items[-1].info["message"] == (  # type: ignore[union-attr]
        f"{path}: corrupt block length 13 at byte {offset} (packet 5); 4 packets read"
    )


def test_corrupt_pcap_record_length_stops_with_an_error(tmp_path: Path) -> None:
    frames = exchange(TcpConversation(CLIENT, SERVER))
    data = bytearray(write_pcap(tmp_path / "x.pcap", frames).read_bytes())
    offset = 24 + sum(16 + len(f) for f in frames[:4])
    struct.pack_into("<I", data, offset + 8, 0x7FFFFFFF)
    (tmp_path / "x.pcap").write_bytes(bytes(data))
    items = read_all(tmp_path / "x.pcap")
    assert summary(items)[:-1] == [(0, "connect"), (0, "c2s", REQUEST)]
    message = items[-1].info["message"]  # type: ignore[union-attr]
    assert message == (
        f"{tmp_path / 'x.pcap'}: corrupt record header (length 2147483647) at byte {offset} "
        "(packet 5); 4 packets read"
    )


def test_truncated_packets_are_counted(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    frames = conv.open()
    whole = conv.send(True, REQUEST)
    frames += [whole[:10], whole[:30], whole[:50]]  # ethernet, IP, TCP headers cut
    stats: dict[str, int] = {}
    items = read_all(write_pcap(tmp_path / "x.pcap", frames), stats=stats)
    assert summary(items) == [(0, "connect")]
    assert stats["truncated"] == 3


def test_snaplen_cut_segment_delivers_what_was_captured(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    frames = [*conv.open(), conv.send(True, REQUEST)[:-4], conv.ack(False)]
    items = read_all(write_pcap(tmp_path / "x.pcap", frames))
    assert summary(items) == [(0, "connect"), (0, "c2s", REQUEST[:-4]), (0, "gap")]


def test_progress_is_reported_up_to_the_total(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    frames = conv.open() + [conv.send(True, bytes(1400)) for _ in range(2000)]
    path = write_pcap(tmp_path / "x.pcap", frames)
    calls: list[tuple[int, int]] = []
    items = list(read_capture(path, progress=lambda done, total: calls.append((done, total))))
    assert len(chunks(items)) == 2000
    total = path.stat().st_size
    assert total > 2 << 20
    assert len(calls) >= 3
    assert all(t == total for _, t in calls)
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)
    assert calls[-1] == (total, total)


def _frames_strategy() -> st.SearchStrategy[list[bytes]]:
    conv = TcpConversation(CLIENT, SERVER)
    valid = exchange(conv, rounds=2)
    mutated = st.tuples(st.sampled_from(valid), st.binary(max_size=8), st.integers(0, 120)).map(
        lambda t: t[0][: t[2]] + t[1] + t[0][t[2] + len(t[1]) :]
    )
    return st.lists(
        st.one_of(st.binary(max_size=120), mutated, st.sampled_from(valid)), max_size=25
    )


@settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    frames=_frames_strategy(),
    linktype=st.sampled_from([0, 1, 101, 108, 113, 147, 228, 229, 276]),
    config=st.sampled_from([CaptureConfig(), CaptureConfig(tcp_ports=frozenset({502, 40001}))]),
)
def test_any_packet_bytes_never_raise(
    tmp_path: Path, frames: list[bytes], linktype: int, config: CaptureConfig
) -> None:
    path = write_pcap(tmp_path / "fuzz.pcap", frames, linktype)
    stats: dict[str, int] = {}
    items = read_all(path, config, stats=stats)
    assert stats["packets"] == len(frames)
    assert not events(items, EventKind.ERROR)


@settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data(), ng=st.booleans())
def test_any_corruption_of_the_file_never_raises(
    tmp_path: Path, data: st.DataObject, ng: bool
) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    path = tmp_path / "x.cap"
    if ng:
        with PcapngWriter(path) as writer:
            writer.add_interface(1)
            for frame in exchange(conv):
                writer.write(T0, frame)
    else:
        write_pcap(path, exchange(conv))
    raw = bytearray(path.read_bytes())
    for _ in range(data.draw(st.integers(1, 6))):
        at = data.draw(st.integers(4, len(raw) - 1))  # keep the magic
        raw[at] = data.draw(st.integers(0, 255))
    path.write_bytes(bytes(raw))
    try:
        items = read_all(path)
    except CaptureError:
        return  # a damaged file header is a clean refusal
    errors = events(items, EventKind.ERROR)
    assert len(errors) <= 1
    if errors:
        assert items[-1] is errors[0]


def test_a_pipe_is_read_too(tmp_path: Path) -> None:
    data = write_pcap(tmp_path / "x.pcap", exchange(TcpConversation(CLIENT, SERVER))).read_bytes()
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)

    def feed() -> None:
        with open(fifo, "wb") as f:
            f.write(gzip.compress(data))

    writer = threading.Thread(target=feed)
    writer.start()
    calls: list[tuple[int, int]] = []
    try:
        items = list(read_capture(fifo, progress=lambda done, total: calls.append((done, total))))
    finally:
        writer.join()
    assert summary(items) == EXPECTED_EXCHANGE
    assert calls[-1][1] == 0  # no size for a pipe
    assert calls[-1][0] > 0


def test_stopping_early_still_fills_stats(tmp_path: Path) -> None:
    conv = TcpConversation(CLIENT, SERVER)
    path = write_pcap(tmp_path / "x.pcap", exchange(conv, rounds=5))
    stats: dict[str, int] = {}
    items = read_capture(path, stats=stats)
    first_chunk = next(i for i in items if isinstance(i, Chunk))
    assert first_chunk.data == REQUEST
    items.close()  # type: ignore[attr-defined]
    assert stats["packets"] == 4  # handshake + the request


_LIMITED_READ = """\
import resource, sys
limit = 3 << 30  # 3 GiB of address space: a 4 GB allocation fails
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
from mbmon.cli import main
sys.exit(main(["read", sys.argv[1]]))
"""


@pytest.mark.parametrize(
    ("header_size", "data_size"), [(32, 0xFFFF0000), (0xFFFFFFF0, 24), (32, 0x7FFFFFFF)]
)
def test_5view_header_claiming_gigabytes_is_not_allocated(
    tmp_path: Path, header_size: int, data_size: int
) -> None:
    """A 5View file header whose sizes claim about 4 GB (the file holds 60 bytes) is a
    clear error, read under a 3 GiB address-space limit: nothing is allocated for it."""
    import subprocess
    import sys

    path = _5view(tmp_path / "x.5vw", [(0, b"x" * 20)])
    data = bytearray(path.read_bytes())
    struct.pack_into("<II", data, 4, header_size, 0x00010000)
    struct.pack_into("<I", data, 12, data_size)
    path.write_bytes(bytes(data))
    proc = subprocess.run(
        [sys.executable, "-c", _LIMITED_READ, str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert "Traceback" not in proc.stderr and "MemoryError" not in proc.stderr, proc.stderr
    assert proc.returncode == 1, proc.stderr
    assert "truncated 5View file header" in proc.stderr


def test_sizes_are_checked_against_the_file_before_reading(tmp_path: Path) -> None:
    """A record whose length claims more than the file holds (50 MB, under the record
    cap) is damage found before anything is read for it: reading the file takes
    memory for the bytes it has, not for what a field claims."""
    import tracemalloc

    frames = exchange(TcpConversation(CLIENT, SERVER))
    path = _5view(tmp_path / "x.5vw", [(0, f) for f in frames])
    data = bytearray(path.read_bytes())
    last = len(data) - len(frames[-1]) - 36  # the last record's header
    struct.pack_into("<I", data, last + 16, 50_000_000)  # its size field
    path.write_bytes(bytes(data))
    tracemalloc.start()
    try:
        items = read_all(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    errors = [i for i in items if isinstance(i, Event) and i.kind is EventKind.ERROR]
    assert errors and "truncated record" in errors[0].info["message"]
    assert f"{len(frames) - 1} packets read" in errors[0].info["message"]  # all before it
    assert peak < 10_000_000, f"{peak} bytes allocated to read a {len(data)}-byte file"
