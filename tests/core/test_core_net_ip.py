"""The core against the reference pipeline on the IP layer: Modbus/TCP over IPv6 (on
every link type, with extension headers, next to IPv4, with holes), Modbus/UDP over
IPv4 and IPv6 (datagram framing: several ADUs, noise, cut ADUs, length 255), byte for
byte, text and JSON (and the MCAP log); IP fragments on a Modbus port read as the
reference reads them (it does not reassemble them: a first fragment is a cut
packet, later ones are skipped), by the file entry and the live one; random
datagram cuts (hypothesis)."""

from __future__ import annotations

import itertools
import json
import tempfile
from pathlib import Path

import pytest
from core_diff import assert_same, require_core, with_core
from gen import (
    T0,
    adus,
    every_function_pair,
    ipv6_segment,
    noisy_stream,
    udp_exchange,
    write_conversation,
    write_frames,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap_diff import assert_same_log

from mbmon.io.pcap import TcpConversation
from mbmon.io.pcap.packets import (
    ACK,
    PSH,
    ethernet_frame,
    ipv4_packet,
    ipv6_packet,
    tcp_header,
    udp_header,
)
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response

V6C, V6S = "[2001:db8::1]:40000", "[2001:db8::2]:502"


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def _v6_conversation(path: Path, linktype: int = 1) -> Path:
    """``write_conversation`` over IPv6 (the same segments, other addresses)."""
    conv = TcpConversation(V6C, V6S, linktype=linktype)
    frames = conv.open()
    frames += [conv.send(c, a) for c, a in adus(every_function_pair())]
    frames += conv.close(True)
    return write_frames(path, [(T0 + i * 0.001, f) for i, f in enumerate(frames)], conv.linktype)


@pytest.mark.parametrize("linktype", [1, 101, 229, 0, 108, 113, 276])
def test_ipv6_on_every_link_type(tmp_path: Path, linktype: int) -> None:
    path = _v6_conversation(tmp_path / "v6.pcap", linktype=linktype)
    assert_same(path, covered=True)
    out, _, _ = with_core(path, as_json=True)
    first = json.loads(out.splitlines()[1])
    assert (first["src"], first["dst"]) == (V6C, V6S)


def test_ipv6_extension_headers(tmp_path: Path) -> None:
    """Hop-by-hop, routing, destination options, an atomic fragment header (offset 0,
    no more fragments: no fragment at all) and AH before TCP, as the reference walks
    them."""
    conv = TcpConversation(V6C, V6S)
    frames = conv.open()
    chains = [
        ((0, b"\x01\x04\0\0\0\0"),),
        ((43, b"\0\0\0\0\0\0"), (60, b"\x01\x02\0\0")),
        ((44, b"\0\0\0\0\0\x07"),),
        ((51, b"\0\0" + b"\x11" * 10),),
        ((0, b""), (60, b""), (51, b"\0" * 6)),
    ]
    for n, (client, adu) in enumerate(adus(every_function_pair()[:8])):
        frames.append(ipv6_segment(conv, client, PSH | ACK, adu, extensions=chains[n % 5]))
    frames += conv.close(False)
    path = write_frames(tmp_path / "ext.pcap", [(T0 + i * 0.01, f) for i, f in enumerate(frames)])
    assert_same(path, covered=True)


def test_ipv4_and_ipv6_side_by_side(tmp_path: Path) -> None:
    """Connections over both in one capture: stream ids in order of appearance, the
    same ports on both families kept apart; one connection with holes over IPv6."""
    c4 = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    c6 = TcpConversation(V6C, V6S)
    c6b = TcpConversation("[::1]:40001", "[::1]:502")
    frames = c6.open() + c4.open() + c6b.open()
    for n, (client, adu) in enumerate(adus(every_function_pair()[:10])):
        frames += [c4.send(client, adu), c6.send(client, adu)]
        if n % 4 == 1:
            c6b.send(client, adu)  # lost: the next ACK passes it
        else:
            frames.append(c6b.send(client, adu))
    frames += c6.close(True) + c4.close(False)
    path = write_frames(tmp_path / "both.pcap", [(T0 + i * 0.001, f) for i, f in enumerate(frames)])
    assert_same(path, covered=True)
    assert_same_log(path, tmp_path, covered=True)


def _req(tid: int) -> bytes:
    return encode_adu(tid, 1, encode_read_request(3, tid, 2))


def _resp(tid: int) -> bytes:
    return encode_adu(tid, 1, encode_read_response(3, [tid, 4]))


@pytest.mark.parametrize("client, server", [("10.0.0.1:40000", "10.0.0.2:502"), (V6C, V6S)])
def test_modbus_udp(tmp_path: Path, client: str, server: str) -> None:
    """Datagrams of one ADU, of several, with noise, a cut ADU (noise at the datagram's
    end), MBAP length 255, an unanswered request (timeout), an unsolicited answer."""
    long_adu = bytes((0, 9, 0, 0, 0, 255, 1, 0x5A)) + bytes(253)
    datagrams = [
        (True, _req(1)),
        (False, _resp(1)),
        (True, _req(2) + _req(3)),
        (False, _resp(3) + _resp(2)),
        (True, b"\x01\x02junk" + _req(4)),
        (False, _resp(4)[:7]),
        (True, _req(5)[:-1]),
        (True, long_adu),
        (False, long_adu),
        (True, _req(6)),
        (False, _resp(77)),
    ]
    datagrams += [(c, a) for c, a in adus(every_function_pair())]
    path = udp_exchange(tmp_path / "udp.pcap", datagrams, client=client, server=server)
    assert_same(path, covered=True)
    out, _, _ = with_core(path, as_json=True)
    records = [json.loads(line) for line in out.splitlines()]
    assert {r["transport"] for r in records if r["kind"] in ("request", "response")} == {"udp"}
    assert any(r["kind"] == "noise" for r in records)
    assert_same_log(path, tmp_path, covered=True)


def test_udp_between_two_modbus_ports_and_many_pairs(tmp_path: Path) -> None:
    """Both ports Modbus ports (the lower one serves), several pairs, TCP beside."""
    frames = []
    for n in range(6):
        cport = 502 if n % 2 else 40000 + n
        d = [(True, _req(n + 1)), (False, _resp(n + 1))]
        sub = udp_exchange(tmp_path / f"u{n}.pcap", d, client=f"10.0.1.{n}:{cport}")
        frames.append(sub.read_bytes()[24:])
    tcp = write_conversation(tmp_path / "t.pcap", adus(every_function_pair()[:4]))
    path = tmp_path / "many.pcap"
    path.write_bytes(tcp.read_bytes() + b"".join(frames))
    assert_same(path, covered=True)
    assert_same(path, covered=True, ports=frozenset({502, 40002}))


def _pieces(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in itertools.pairwise(points) if b > a]


@settings(
    max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    seed=st.integers(0, 2**16),
    client_cuts=st.lists(st.integers(0, 10_000), max_size=20),
    server_cuts=st.lists(st.integers(0, 10_000), max_size=20),
    v6=st.booleans(),
)
def test_random_datagrams(seed: int, client_cuts: list[int], server_cuts: list[int], v6: bool):
    """A noisy stream cut into datagrams anywhere: each datagram framed alone."""
    stream = noisy_stream(seed)
    client = b"".join(a for c, a in stream if c)
    server = b"".join(a for c, a in stream if not c)
    cs, ss = _pieces(client, client_cuts), _pieces(server, server_cuts)
    datagrams: list[tuple[bool, bytes]] = []
    while cs or ss:
        if cs:
            datagrams.append((True, cs.pop(0)))
        if ss:
            datagrams.append((False, ss.pop(0)))
    ends = (V6C, V6S) if v6 else ("10.0.0.1:40000", "10.0.0.2:502")
    with tempfile.TemporaryDirectory() as tmp:
        path = udp_exchange(Path(tmp) / "r.pcap", datagrams, client=ends[0], server=ends[1])
        assert_same(path, covered=True)


def _fragments() -> list[tuple[str, bytes]]:
    """Fragments on a Modbus port, IPv4 and IPv6, TCP and UDP: first fragments that
    hold the whole segment or datagram (more-fragments set), first fragments that cut
    an ADU or a datagram short, later fragments."""
    base = adus(every_function_pair()[:2])
    adu = base[0][1]
    seg = tcp_header("10.0.0.1", "10.0.0.2", 40000, 502, 1001, 5001, PSH | ACK, adu)
    dgram = udp_header("10.0.0.1", "10.0.0.2", 40000, 502, adu)
    seg6 = tcp_header("2001:db8::1", "2001:db8::2", 40000, 502, 1001, 5001, PSH | ACK, adu)
    dgram6 = udp_header("2001:db8::1", "2001:db8::2", 40000, 502, adu)

    def v4(proto: int, body: bytes, frag: int) -> bytes:
        return ethernet_frame(
            ipv4_packet("10.0.0.1", "10.0.0.2", proto, body, flags_fragment=frag), 0x0800
        )

    def v6(proto: int, body: bytes, frag: bytes) -> bytes:
        return ethernet_frame(
            ipv6_packet(
                "2001:db8::1", "2001:db8::2", proto, body, extensions=((44, frag + bytes(4)),)
            ),
            0x86DD,
        )

    return [
        ("first4", v4(6, seg, 0x2000)),
        ("first4_cut", v4(6, seg[:28], 0x2000)),
        ("later4", v4(6, seg[8:], 0x0001)),
        ("udp", v4(17, dgram, 0x2000)),
        ("udp_cut", v4(17, dgram[:16], 0x2000)),
        ("udp_later", v4(17, dgram[8:], 0x0002)),
        ("first6", v6(6, seg6, b"\0\x01")),
        ("first6_cut", v6(6, seg6[:26], b"\0\x01")),
        ("later6", v6(6, seg6, b"\0\x09")),
        ("udp6", v6(17, dgram6, b"\0\x01")),
        ("udp6_cut", v6(17, dgram6[:12], b"\0\x01")),
    ]


def test_fragments_on_a_modbus_port(tmp_path: Path) -> None:
    """The reference does not reassemble IP fragments: a first fragment is a cut
    packet (the bytes it holds go on as a snap-cut packet's; a datagram longer than
    it is none), later fragments are skipped. The core reads them the same, in the
    middle of a conversation and of a UDP exchange."""
    base = adus(every_function_pair()[:2])
    plain = write_conversation(tmp_path / "plain.pcap", base, close=None).read_bytes()
    for name, frame in _fragments():
        extra = write_frames(tmp_path / f"{name}x.pcap", [(T0 + 9, frame)]).read_bytes()[24:]
        more = write_conversation(tmp_path / "more.pcap", base, handshake=False, close=None)
        path = tmp_path / f"{name}.pcap"
        path.write_bytes(plain + extra + more.read_bytes()[24:])
        assert_same(path, covered=True)
