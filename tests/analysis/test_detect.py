"""Modbus on any TCP port, found by structure (mbmon.analysis.detect through the dissector):
real captures moved to other ports, other industrial and web protocols, random payloads."""

from __future__ import annotations

import json
import os
import random
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.analysis.detect import MAX_CANDIDATES
from mbmon.io import pcap as pw
from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.model import Chunk, Event, EventKind, Transport
from mbmon.pipeline import Pipeline
from mbmon.protocol.crc import add_crc
from mbmon.protocol.mbap import encode_adu
from mbmon.sources.dissect import CaptureConfig, Dissector
from mbmon.sources.pcapfile import read_capture

REPO = Path(__file__).resolve().parents[2]
REAL = REPO / ".." / "shared" / "captures" / "real"
DETECT = CaptureConfig(detect=True)

READ_REQ = encode_adu(7, 1, bytes.fromhex("0300C80002"))  # read R200..R201
READ_RESP = encode_adu(7, 1, bytes.fromhex("030400010002"))
WRITE_REQ = encode_adu(8, 1, bytes.fromhex("0600C80005"))
WRITE_RESP = encode_adu(8, 1, bytes.fromhex("0600C80005"))


def exchange(
    conv: TcpConversation, pairs: list[tuple[bytes, bytes]], *, t0: float = 1.0, close: bool = True
) -> list[tuple[float, bytes]]:
    """A connection with a handshake, each request and its answer 10 ms apart, a close."""
    packets = [(t0, f) for f in conv.open()]
    t = t0
    for request, response in pairs:
        t += 0.01
        packets.append((t, conv.send(True, request)))
        t += 0.01
        packets.append((t, conv.send(False, response)))
    if close:
        packets += [(t + 0.01, f) for f in conv.close()]
    return packets


def dissect(packets: list[tuple[float, bytes]], config: CaptureConfig = DETECT, link: int = 1):
    d = Dissector(config)
    out: list[Chunk | Event] = []
    for ts, frame in packets:
        out += d.packet_bytes(ts, link, frame)
    out += d.finish(packets[-1][0] if packets else 0.0)
    return d, out


def streams(items: list[Chunk | Event]) -> set[tuple[str, str, str]]:
    return {
        (i.stream.transport.value, i.stream.client, i.stream.server)
        for i in items
        if i.stream is not None
    }


def described(items: list[Chunk | Event]) -> list[tuple[float, str, str]]:
    return [
        (i.ts, i.kind.value if isinstance(i, Event) else i.direction.value,
         "" if isinstance(i, Event) else i.data.hex())
        for i in items
    ]  # fmt: skip


# --------------------------------------------------------------------------- byte tables


def test_mbap_on_port_1502_becomes_the_same_stream_as_with_port_named() -> None:
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:1502")
    packets = exchange(conv, [(READ_REQ, READ_RESP), (WRITE_REQ, WRITE_RESP)])
    detector, found = dissect(packets)
    _, named = dissect(packets, CaptureConfig(tcp_ports=frozenset({502, 1502})))
    assert streams(found) == {("tcp", "10.0.0.2:40000", "10.0.0.1:1502")}
    # nothing lost and nothing re-timed: the CONNECT and the first exchange that were
    # held while deciding come out exactly as if the port had been named
    assert described(found) == described(named)
    assert described(found)[0] == (1.0, "connect", "")
    assert detector.detected() == [("tcp", 1502, "10.0.0.1:1502", 1)]
    assert detector.stats()["modbus_packets"] == len(packets)
    assert detector.stats()["non_modbus"] == 0


def test_the_server_is_known_after_one_connection_proved_it() -> None:
    """A later connection to a promoted endpoint is a stream from its first packet, even
    one that never gets an answer; another server's unanswered request is not."""
    first = exchange(TcpConversation("10.0.0.2:40000", "10.0.0.1:1502"), [(READ_REQ, READ_RESP)])
    later = TcpConversation("10.0.0.3:40001", "10.0.0.1:1502")
    lone = TcpConversation("10.0.0.3:40002", "10.0.0.9:1502")
    packets = first + [(5.0, f) for f in later.open()] + [(5.1, later.send(True, READ_REQ))]
    packets += [(6.0, f) for f in lone.open()] + [(6.1, lone.send(True, READ_REQ))]
    d, out = dissect(packets)
    assert streams(out) == {
        ("tcp", "10.0.0.2:40000", "10.0.0.1:1502"),
        ("tcp", "10.0.0.3:40001", "10.0.0.1:1502"),
    }
    assert d.detected() == [("tcp", 1502, "10.0.0.1:1502", 2)]


def test_connections_waiting_when_their_server_is_proved_are_replayed_too() -> None:
    """Two connections to one server: the first has no answer yet when the second
    proves the server; the first one's held bytes are not lost."""
    a = TcpConversation("10.0.0.2:40000", "10.0.0.1:1502")
    b = TcpConversation("10.0.0.2:40001", "10.0.0.1:1502")
    packets = [(1.0, f) for f in a.open()] + [(1.1, a.send(True, READ_REQ))]
    packets += exchange(b, [(WRITE_REQ, WRITE_RESP)], t0=1.2)
    packets += [(1.5, a.send(False, READ_RESP))]
    _, found = dissect(packets)
    _, named = dissect(packets, CaptureConfig(tcp_ports=frozenset({1502})))
    assert sorted(described(found)) == sorted(described(named))
    assert len(streams(found)) == 2


@pytest.mark.parametrize(
    ("name", "ask", "answer"),
    [
        ("one lucky header, garbage answer", READ_REQ, b"\x00\x07\x00\x00\x00\x05\x01\x03"),
        (
            "answer with another transaction id",
            READ_REQ,
            encode_adu(9, 1, bytes.fromhex("030400010002")),
        ),
        ("answer for another unit", READ_REQ, encode_adu(7, 2, bytes.fromhex("030400010002"))),
        (
            "answer with another function code",
            READ_REQ,
            encode_adu(7, 1, bytes.fromhex("040400010002")),
        ),
        ("answer of the wrong length", READ_REQ, encode_adu(7, 1, bytes.fromhex("0304000100"))),
        ("request of the wrong length", encode_adu(7, 1, bytes.fromhex("0300C800")), READ_RESP),
        ("a protocol id that is not 0", b"\x00\x07\x00\x01" + READ_REQ[4:], READ_RESP),
    ],
)
def test_no_promotion_without_a_consistent_answer(name: str, ask: bytes, answer: bytes) -> None:
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:1502")
    d, out = dissect(exchange(conv, [(ask, answer)]))
    assert streams(out) == set(), name
    assert d.detected() == []


def test_a_request_without_answer_is_no_stream() -> None:
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:1502")
    packets = [(1.0, f) for f in conv.open()] + [(1.1, conv.send(True, READ_REQ))]
    assert dissect(packets)[1] == []


def test_the_answer_must_come_after_the_request() -> None:
    """The server "answers" first (both sides sending the same ADU): no promotion on the
    server's bytes; the client is the side that sent the SYN."""
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:1502")
    packets = [(1.0, f) for f in conv.open()]
    packets += [(1.1, conv.send(False, READ_RESP)), (1.2, conv.send(True, READ_REQ))]
    assert dissect(packets)[1] == []


def test_rtu_over_tcp_is_found_by_crc() -> None:
    request = add_crc(bytes.fromhex("110300C80002"))
    response = add_crc(bytes.fromhex("1103040001000A"))
    exception = add_crc(bytes.fromhex("118302"))
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:4001")
    packets = exchange(conv, [(request, response), (request, exception)])
    d, out = dissect(packets)
    assert streams(out) == {("rtu-over-tcp", "10.0.0.2:40000", "10.0.0.1:4001")}
    _, named = dissect(packets, CaptureConfig(rtu_ports=frozenset({4001})))
    assert described(out) == described(named)
    assert d.detected() == [("rtu-over-tcp", 4001, "10.0.0.1:4001", 1)]
    # a bad CRC in the answer proves nothing
    bad = response[:-1] + bytes([response[-1] ^ 1])
    other = TcpConversation("10.0.0.2:40000", "10.0.0.1:4002")
    assert dissect(exchange(other, [(request, bad)]))[1] == []


def test_npcap_loopback_capture_on_port_1502(tmp_path: Path) -> None:
    """A Windows loopback capture (Npcap: link type NULL) of a server on port 1502."""
    path = tmp_path / "loopback.pcap"
    conv = TcpConversation("127.0.0.1:50123", "127.0.0.1:1502", linktype=pw.LINKTYPE_NULL)
    with PcapWriter(path, pw.LINKTYPE_NULL) as w:
        for ts, frame in exchange(conv, [(READ_REQ, READ_RESP)] * 3):
            w.write(ts, frame)
    records = list(Pipeline().run(read_capture(path, DETECT)))
    frames = [r for r in records if r.frame is not None]
    assert len(frames) == 6
    assert {r.stream.server for r in frames} == {"127.0.0.1:1502"}
    assert all(r.latency is not None for r in frames if r.request is not None)
    assert [r.event.kind for r in records if r.event is not None] == [
        EventKind.CONNECT,
        EventKind.DISCONNECT,
    ]


def test_detection_off_is_the_default_and_the_one_switch() -> None:
    """Without detect the dissector has no detector: one value a compiled core reads."""
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:1502")
    packets = exchange(conv, [(READ_REQ, READ_RESP)])
    d, out = dissect(packets, CaptureConfig())
    assert d.detector is None and out == [] and d.detected() == []
    assert CaptureConfig().detect is False and DETECT.detect is True


@settings(max_examples=60, deadline=None)
@given(cuts=st.lists(st.integers(1, 40), min_size=1, max_size=8))
def test_any_segmentation_gives_the_same_chunks(cuts: list[int]) -> None:
    """Pipelined ADUs cut into segments anywhere (inside headers too): the same bytes,
    times and stream as with the port named."""
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:1502")
    client = READ_REQ + WRITE_REQ
    server = READ_RESP + WRITE_RESP
    packets = [(1.0, f) for f in conv.open()]
    t = 1.0
    for data, from_client in ((client, True), (server, False)):
        pos = 0
        for cut in [*cuts, len(data)]:
            if pos >= len(data):
                break
            t += 0.001
            packets.append((t, conv.send(from_client, data[pos : pos + cut])))
            pos += cut
    _, found = dissect(packets)
    _, named = dissect(packets, CaptureConfig(tcp_ports=frozenset({1502})))
    assert described(found) == described(named)
    assert len(streams(found)) == 1


# --------------------------------------------------------------------------- other protocols


def _tpkt(payload: bytes) -> bytes:
    return b"\x03\x00" + struct.pack("!H", 4 + len(payload)) + payload


def _enip(command: int, data: bytes, session: int = 0) -> bytes:
    return struct.pack("<HHII8sI", command, len(data), session, 0, b"\0" * 8, 0) + data


def _tls_record(kind: int, body: bytes) -> bytes:
    return bytes([kind, 3, 3]) + struct.pack("!H", len(body)) + body


OTHER_PROTOCOLS: dict[str, tuple[int, list[tuple[bytes, bytes]]]] = {
    "S7comm (TPKT/COTP)": (
        102,
        [
            (
                _tpkt(bytes.fromhex("11e00000000100c0010ac1020100c2020102")),
                _tpkt(bytes.fromhex("11d00001000100c0010ac1020100c2020102")),
            ),
            (
                _tpkt(bytes.fromhex("02f080320100000000000800000f00000100010001e0")),
                _tpkt(bytes.fromhex("02f080320300000000000800000000f0000001000100f0")),
            ),
            (
                _tpkt(bytes.fromhex("02f080320100000100000e00000401120a10020001000184000000")),
                _tpkt(bytes.fromhex("02f0803203000001000002000600000401ff04001000ff")),
            ),
        ],
    ),
    "EtherNet/IP": (
        44818,
        [
            (_enip(0x0065, b"\x01\x00\x00\x00"), _enip(0x0065, b"\x01\x00\x00\x00", 0x12345678)),
            (_enip(0x0063, b""), _enip(0x0063, b"\x01\x00\x0c\x00" + b"\x00" * 40)),
            (
                _enip(
                    0x006F,
                    b"\x00" * 6
                    + b"\x02\x00\x00\x00\x00\x00\xb2\x00\x06\x00\x01\x02\x20\x01\x24\x01",
                    0x12345678,
                ),
                _enip(
                    0x006F,
                    b"\x00" * 6 + b"\x02\x00\x00\x00\x00\x00\xb2\x00\x04\x00\x81\x00\x00\x00",
                    0x12345678,
                ),
            ),
        ],
    ),
    "HTTP": (
        8080,
        [
            (
                b"GET / HTTP/1.1\r\nHost: plc\r\n\r\n",
                b"HTTP/1.1 200 OK\r\nContent-Length: 5\r\n\r\nhello",
            ),
            (b"GET /a HTTP/1.1\r\nHost: plc\r\n\r\n", b"HTTP/1.1 404 Not Found\r\n\r\n"),
        ],
    ),
    "TLS": (
        443,
        [
            (
                _tls_record(
                    22,
                    b"\x01\x00\x00\x2c\x03\x03"
                    + bytes(range(32))
                    + b"\x00\x00\x02\x13\x01\x01\x00",
                ),
                _tls_record(
                    22, b"\x02\x00\x00\x26\x03\x03" + bytes(range(32, 64)) + b"\x00\x13\x01\x00"
                ),
            ),
            (_tls_record(23, bytes(range(64))), _tls_record(23, bytes(range(64, 160)))),
        ],
    ),
    "Modbus-like headers with other ids (a fuzzer)": (
        5020,
        [
            (
                encode_adu(1, 1, bytes.fromhex("0300000001")),
                encode_adu(2, 1, bytes.fromhex("03020000")),
            ),
            (
                encode_adu(3, 1, bytes.fromhex("0300000001")),
                encode_adu(3, 9, bytes.fromhex("03020000")),
            ),
        ],
    ),
}


def test_s7comm_ethernet_ip_http_and_tls_give_no_false_stream(tmp_path: Path) -> None:
    """A capture mixing other protocols with Modbus on 502: only the Modbus stream,
    the others counted as non-Modbus; the busiest-ports hint still works."""
    path = tmp_path / "mixed.pcap"
    with PcapWriter(path) as w:
        t = 1.0
        for n, (port, pairs) in enumerate(OTHER_PROTOCOLS.values()):
            conv = TcpConversation(f"10.0.1.{n + 2}:{41000 + n}", f"10.0.0.{n + 5}:{port}")
            for ts, frame in exchange(conv, pairs * 5, t0=t):
                w.write(ts, frame)
            t += 1.0
        modbus = TcpConversation("10.0.1.99:42000", "10.0.0.1:502")
        for ts, frame in exchange(modbus, [(READ_REQ, READ_RESP)], t0=t):
            w.write(ts, frame)
    stats: dict[str, object] = {}
    items = list(read_capture(path, DETECT, stats=stats))
    assert streams(items) == {("tcp", "10.0.1.99:42000", "10.0.0.1:502")}
    assert stats["detected"] == []
    assert stats["non_modbus"] > 0


def test_random_payloads_give_no_false_stream() -> None:
    """10^5 connections exchanging random bytes, a fifth of them dressed with a
    plausible MBAP header (protocol id 0, a length that fits): 0 streams."""
    rng = random.Random(25)
    d = Dissector(DETECT)
    made = 0
    for n in range(100_000):
        addrs = struct.pack("!II", 0x0A000000 | n, 0x0A100000 | (n * 7 & 0xFFFF))
        sport, dport = 1024 + n % 60000, 1 + rng.randrange(65535)
        if dport == 502:
            dport = 503
        payloads = []
        for _ in range(2):
            body = rng.randbytes(rng.randrange(1, 40))
            if n % 5 == 0:
                body = (
                    rng.randbytes(2)
                    + b"\0\0"
                    + struct.pack("!H", len(body) + 1)
                    + bytes([1])
                    + body
                )
            payloads.append(body)
        out: list[object] = []
        d._detect(float(n), (addrs, sport, dport), 1000, 0, pw.PSH | pw.ACK, payloads[0], out)
        rev = (addrs[4:] + addrs[:4], dport, sport)
        d._detect(
            float(n) + 0.5, rev, 5000, 1000 + len(payloads[0]), pw.PSH | pw.ACK, payloads[1], out
        )
        made += len(out)
    assert made == 0
    assert d.next_id == 0 and d.detected() == []
    assert len(d.detector._order) <= MAX_CANDIDATES  # type: ignore[union-attr]


def test_undecided_connections_are_bounded() -> None:
    d = Dissector(DETECT)
    for n in range(3 * MAX_CANDIDATES):
        conv = TcpConversation(f"10.0.{n >> 8}.{n & 255}:40000", "10.1.0.1:1502")
        for frame in conv.open():
            d.packet_bytes(float(n), 1, frame)
    assert len(d.detector._order) == MAX_CANDIDATES  # type: ignore[union-attr]


# --------------------------------------------------------------------------- real captures


def _move_port(src: Path, dst: Path, old: int, new: int) -> bool:
    """Copy a classic Ethernet pcap with TCP port ``old`` rewritten to ``new``
    (checksums are not checked by readers of this project); False if not such a file."""
    data = src.read_bytes()
    if data[:4] not in (b"\xd4\xc3\xb2\xa1", b"\x4d\x3c\xb2\xa1"):
        return False
    if struct.unpack_from("<I", data, 20)[0] != 1:
        return False
    out = bytearray(data[:24])
    pos = 24
    while pos + 16 <= len(data):
        incl = struct.unpack_from("<I", data, pos + 8)[0]
        rec = bytearray(data[pos + 16 : pos + 16 + incl])
        if len(rec) >= 38 and rec[12:14] == b"\x08\x00" and rec[23] == 6:
            tcp = 14 + (rec[14] & 15) * 4
            for at in (tcp, tcp + 2):
                if len(rec) >= at + 2 and struct.unpack_from("!H", rec, at)[0] == old:
                    struct.pack_into("!H", rec, at, new)
        out += data[pos : pos + 16] + rec
        pos += 16 + incl
    dst.write_bytes(bytes(out))
    return True


def _frames(path: Path, config: CaptureConfig) -> list[tuple[float, str, str, str]]:
    records = Pipeline().run(read_capture(path, config))
    return sorted(
        (r.ts, r.stream.client.rsplit(":", 1)[0], r.kind.value, r.frame.raw.hex())
        for r in records
        if r.frame is not None and r.stream is not None
    )


# Captures where some connection never shows a structurally sound answered request
# (so it stays unpromoted by design): a request the server never answers (crash), TCP
# holes before the first answer (the fuzzer traces), MBAP lengths that break the
# framing at the start of a connection (Digital Bond part 1, and Arkime's merge of it).
NOT_ALL_PROVABLE = {
    "tcp__emreekin__crash.pcap",
    "tcp__zeek__fuzz-72.pcap",
    "tcp__zeek__fuzz-1011.pcap",
    "tcp__digitalbond__modbus_test_data_part1.pcap",
    "tcp__arkime__modbus_merged.pcap",
}
REAL_PCAPS = sorted(p.name for p in REAL.glob("tcp__*.pcap")) if REAL.is_dir() else []


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/captures/real absent")
@pytest.mark.parametrize("name", REAL_PCAPS)
def test_real_capture_moved_to_port_1502_is_found(name: str, tmp_path: Path) -> None:
    """The public captures with their server port rewritten from 502 to 1502: detection
    finds the same frames (same bytes and times) as reading the original on 502."""
    moved = tmp_path / "moved.pcap"
    if not _move_port(REAL / name, moved, 502, 1502):
        pytest.skip(f"{name} is not a classic Ethernet pcap")
    found = _frames(moved, DETECT)
    original = _frames(REAL / name, CaptureConfig())
    if name in NOT_ALL_PROVABLE:
        assert set(found) <= set(original)
    else:
        assert found == original
        assert original


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/captures/real absent")
@pytest.mark.parametrize(
    "name", sorted(p.name for p in REAL.glob("tcp__*")) if REAL.is_dir() else []
)
def test_real_captures_gain_no_false_stream(name: str) -> None:
    """Detection on every public capture (S7comm in modbusBig, SMB in the lemay files,
    HTTP in kb221svs, LAN noise in the emreekin files): the streams are the ones on
    port 502, nothing more."""
    stats: dict[str, object] = {}
    with_detection = streams(list(read_capture(REAL / name, DETECT, stats=stats)))
    assert with_detection == streams(list(read_capture(REAL / name, CaptureConfig())))
    assert stats["detected"] == []


# --------------------------------------------------------------------------- command line


def _write(path: Path, packets: list[tuple[float, bytes]]) -> None:
    with PcapWriter(path) as w:
        for ts, frame in packets:
            w.write(ts, frame)


def test_read_finds_port_1502_and_says_so(tmp_path: Path) -> None:
    path = tmp_path / "cell.pcap"
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:1502")
    _write(path, exchange(conv, [(READ_REQ, READ_RESP), (WRITE_REQ, WRITE_RESP)]))
    run = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", str(path), "--json"],
        capture_output=True, text=True, cwd=REPO, timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    lines = [json.loads(line) for line in run.stdout.splitlines()]
    assert [r["kind"] for r in lines if r["kind"] != "event"] == ["request", "response"] * 2
    assert (
        "found Modbus/TCP on port 1502 by its structure: 1 connection to 10.0.0.1:1502"
        in run.stderr
    )
    off = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", str(path), "--no-detect"],
        capture_output=True, text=True, cwd=REPO, timeout=120,
    )  # fmt: skip
    assert off.returncode == 0 and off.stdout == ""
    assert "no Modbus found on port 502;" in off.stderr and "try --port 1502" in off.stderr
    forced = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", str(path), "--no-detect", "--port", "1502", "-q",
         "-w", str(tmp_path / "x.jsonl")],
        capture_output=True, text=True, cwd=REPO, timeout=120,
    )  # fmt: skip
    assert forced.returncode == 0, forced.stderr
    assert (tmp_path / "x.jsonl").read_text().count('"kind":"request"') == 2


def test_transport_of_a_detected_rtu_stream_reaches_records(tmp_path: Path) -> None:
    request = add_crc(bytes.fromhex("110300C80002"))
    response = add_crc(bytes.fromhex("1103040001000A"))
    path = tmp_path / "rtu.pcap"
    _write(
        path, exchange(TcpConversation("10.0.0.2:40000", "10.0.0.1:4001"), [(request, response)])
    )
    records = [r for r in Pipeline().run(read_capture(path, DETECT)) if r.frame is not None]
    assert [r.stream.transport for r in records] == [Transport.RTU_OVER_TCP] * 2
    assert records[1].request is not None and records[1].frame.pdu.values == (1, 10)


# --------------------------------------------------------------------------- live


def test_the_default_kernel_filter_passes_every_tcp_packet_only_while_detecting() -> None:
    from mbmon.sources.sniff import capture_filter

    ports = frozenset({502, 1502})
    assert capture_filter(CaptureConfig(tcp_ports=ports)) == (
        "tcp port 502 or udp port 502 or tcp port 1502 or udp port 1502"
    )
    assert capture_filter(CaptureConfig(tcp_ports=ports, detect=True)) == (
        "tcp or udp port 502 or udp port 1502"
    )


@pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() != 0,
    reason="live capture needs root (an AF_PACKET socket); CI runs as root",
)
def test_sniff_finds_a_server_on_an_unnamed_port() -> None:
    """``sniff lo`` without --port while the simulator serves on a free port: the
    requests and answers are shown and the summary names the port. The kernel filter
    is narrowed with -f to that port only so that other loopback traffic of the
    machine stays out of the test; no port is named to mbmon."""
    import select
    import signal
    import socket
    import time

    from mbmon.sim import SimServer

    with SimServer() as sim:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "sniff", "lo", "-f", f"tcp port {sim.port}", "--json"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO,
        )  # fmt: skip
        try:
            assert proc.stderr is not None and proc.stdout is not None
            assert b"sniffing" in proc.stderr.readline()
            with socket.create_connection((sim.host, sim.port)) as conn:
                for tid in (1, 2, 3):
                    conn.sendall(encode_adu(tid, 1, bytes.fromhex("04012C0002")))  # IR300..301
                    assert conn.recv(64)[7] == 0x04
            out = b""
            end = time.monotonic() + 30
            while out.count(b'"kind":"response"') < 3 and time.monotonic() < end:
                if select.select([proc.stdout], [], [], 0.5)[0]:
                    out += os.read(proc.stdout.fileno(), 65536)
            proc.send_signal(signal.SIGINT)
            rest, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    records = [json.loads(line) for line in (out + rest).decode().splitlines()]
    frames = [(r["kind"], r["pdu"][:2]) for r in records if r["kind"] != "event"]
    assert frames == [("request", "04"), ("response", "04")] * 3
    assert f"found Modbus/TCP on port {sim.port} by its structure" in err.decode()
