"""The dissector's Ethernet/IPv4/TCP fast path against its general path: the same
random packets (well formed or damaged: lengths, offsets, fragments, options,
cut frames, Modbus and other ports, with and without port detection) give the
same chunks, events, counters and port figures when every packet goes the
general way (``Dissector.packet_general``)."""

from __future__ import annotations

import struct
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response
from mbmon.sources.dissect import CaptureConfig, Dissector

HOSTS = [bytes([10, 0, 0, 1]), bytes([10, 0, 0, 2]), bytes([10, 0, 0, 3])]
PORTS = [502, 40000, 40001, 8080, 1502]
FLAGS = [0x18, 0x10, 0x02, 0x12, 0x11, 0x19, 0x04, 0x14, 0x08, 0x00, 0x03]


@st.composite
def payloads(draw: Any) -> bytes:
    kind = draw(st.sampled_from(["none", "request", "response", "junk"]))
    tid = draw(st.integers(0, 3))
    if kind == "request":
        return encode_adu(tid, 1, encode_read_request(3, draw(st.integers(0, 50)), 2))
    if kind == "response":
        return encode_adu(tid, 1, encode_read_response(3, [draw(st.integers(0, 0xFFFF)), 1]))
    if kind == "junk":
        return draw(st.binary(min_size=1, max_size=30))
    return b""


@st.composite
def packets(draw: Any) -> bytes:
    """One Ethernet frame: IPv4/TCP as a rule, now and then damaged or something else."""
    src, dst = draw(st.sampled_from(HOSTS)), draw(st.sampled_from(HOSTS))
    sport, dport = draw(st.sampled_from(PORTS)), draw(st.sampled_from(PORTS))
    seq = draw(st.sampled_from([1000, 1001, 1013, 1025, 5000, 5001, 5012, 0xFFFFFFF8]))
    ack = draw(st.sampled_from([0, 1001, 1013, 5001, 5012, 9999]))
    flags = draw(st.sampled_from(FLAGS))
    payload = draw(payloads())
    tcp_options = b"\x01\x01\x01\x01" * draw(st.sampled_from([0, 0, 1, 3]))
    doff = (20 + len(tcp_options)) // 4
    if draw(st.integers(0, 7)) == 0:
        doff = draw(st.integers(0, 15))
    tcp = (
        struct.pack(">HHIIHHHH", sport, dport, seq, ack, (doff << 12) | flags, 65535, 0, 0)
        + tcp_options
        + payload
    )
    ip_options = b"\x01\x01\x01\x01" * draw(st.sampled_from([0, 0, 0, 1]))
    ihl = (20 + len(ip_options)) // 4
    proto = draw(st.sampled_from([6, 6, 6, 6, 17]))
    total = 20 + len(ip_options) + len(tcp)
    if draw(st.integers(0, 5)) == 0:
        total = draw(st.sampled_from([0, 10, 20, 39, 40, 41, total - 1, total + 1, total + 50]))
    frag = draw(st.sampled_from([0, 0, 0, 0x4000, 0x2000, 0x0010, 0x2010]))
    version = draw(st.sampled_from([4] * 12 + [6]))
    ip = (
        struct.pack(
            ">BBHHHBBH4s4s", (version << 4) | ihl, 0, total, 1, frag, 64, proto, 0, src, dst
        )
        + ip_options
    )
    ethertype = draw(st.sampled_from([0x0800] * 12 + [0x86DD, 0x0806]))
    frame = b"\x00\x11\x22\x33\x44\x55\x66\x77\x88\x99\xaa\xbb" + struct.pack(">H", ethertype)
    frame += ip + tcp
    frame += b"\x00" * draw(st.sampled_from([0, 0, 0, 6]))  # Ethernet padding
    if draw(st.integers(0, 5)) == 0:  # cut by the snap length
        frame = frame[: draw(st.integers(0, len(frame)))]
    return frame


def _run(frames: list[bytes], detect: bool, general: bool) -> tuple[Any, ...]:
    d = Dissector(CaptureConfig(detect=detect), idle_timeout=5.0, hole_timeout=0.5)
    take = d.packet_general if general else d.packet
    out: list[Any] = []
    for i, frame in enumerate(frames):
        take(100.0 + i * 0.25, 1, 0, frame, 0, len(frame), out)
    out.extend(d.finish(100.0 + len(frames)))
    return (
        out,
        d.stats(),
        d.busiest_ports(10),
        d.good_ts,
        d.detected() if detect else None,
    )


@settings(max_examples=300, deadline=None)
@given(st.lists(packets(), max_size=30), st.booleans())
def test_the_fast_path_gives_what_the_general_path_gives(frames: list[bytes], detect: bool) -> None:
    assert _run(frames, detect, general=False) == _run(frames, detect, general=True)


def test_a_well_formed_modbus_frame_comes_out_the_same_either_way() -> None:
    """A plain request (which the fast path takes) gives its chunk both ways."""
    adu = encode_adu(1, 1, encode_read_request(3, 0, 2))
    tcp = struct.pack(">HHIIHHHH", 40000, 502, 1000, 0, (5 << 12) | 0x18, 65535, 0, 0) + adu
    ip = struct.pack(
        ">BBHHHBBH4s4s", 0x45, 0, 20 + len(tcp), 1, 0x4000, 64, 6, 0, HOSTS[0], HOSTS[1]
    )
    frame = b"\x00" * 12 + b"\x08\x00" + ip + tcp
    fast, general = _run([frame], False, False), _run([frame], False, True)
    assert fast == general
    assert [item.data for item in fast[0] if hasattr(item, "data")] == [adu]


def _frame(total: int, sport: int, dport: int, body: bytes = b"x" * 10) -> bytes:
    tcp = struct.pack(">HHIIHHHH", sport, dport, 1000, 0, (5 << 12) | 0x18, 65535, 0, 0) + body
    ip = struct.pack(">BBHHHBBH4s4s", 0x45, 0, total, 1, 0, 64, 6, 0, HOSTS[0], HOSTS[1])
    return b"\x00" * 12 + b"\x08\x00" + ip + tcp


def test_an_ip_length_shorter_than_the_headers_is_damage_on_any_port() -> None:
    """The cases the differential test found: an IP length of 30 (TCP header cut)
    on other ports was counted as a non-Modbus packet by the fast path; an IP
    length of 10 on Modbus ports made the packet the last good one."""
    for general in (False, True):
        _out, stats, _ports, good_ts, _ = _run([_frame(30, 40000, 8080)], False, general)
        assert (stats["non_modbus"], stats["truncated"], good_ts) == (0, 1, None), general
        _out, stats, _ports, good_ts, _ = _run([_frame(10, 40000, 502)], False, general)
        assert (stats["modbus_packets"], stats["malformed"], good_ts) == (0, 1, None), general
