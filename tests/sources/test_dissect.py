"""The packet dissector (mbmon.sources.dissect): packets in, chunks and events out,
state that stays bounded, time that reaches reassembly."""

from __future__ import annotations

import itertools
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from mbmon.io import pcap as pw
from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.protocol.mbap import encode_adu
from mbmon.sources.dissect import CLOSED_LINGER, CaptureConfig, Dissector
from mbmon.sources.pcapfile import read_capture

REPO = Path(__file__).resolve().parents[2]
ETH = pw.LINKTYPE_ETHERNET
PSH_ACK = pw.PSH | pw.ACK
REQUEST = encode_adu(1, 1, bytes.fromhex("0300000001"))
RESPONSE = encode_adu(1, 1, bytes.fromhex("03020007"))


def conversation(client_port: int = 40000) -> TcpConversation:
    return TcpConversation(f"10.0.0.2:{client_port}", "10.0.0.1:502")


def feed(d: Dissector, packets: list[tuple[float, bytes]]) -> list[Chunk | Event]:
    out: list[Chunk | Event] = []
    for ts, frame in packets:
        out += d.packet_bytes(ts, ETH, frame)
    return out


def kinds(items: list[Chunk | Event]) -> list[str]:
    return [
        f"{i.kind.value}" if isinstance(i, Event) else f"chunk@{i.ts}:{i.data.hex()}" for i in items
    ]


# --------------------------------------------------------------------------- API


def test_packet_bytes_gives_chunks_and_events_of_one_packet() -> None:
    conv = conversation()
    d = Dissector(CaptureConfig())
    out = feed(d, [(1.0, f) for f in conv.open()] + [(1.5, conv.send(True, REQUEST))])
    assert kinds(out) == ["connect", f"chunk@1.5:{REQUEST.hex()}"]
    stream = out[1].stream
    assert (stream.id, stream.transport, stream.client, stream.server) == (
        0,
        Transport.TCP,
        "10.0.0.2:40000",
        "10.0.0.1:502",
    )
    assert d.next_deadline() is not None  # the idle clock runs


def test_new_stream_lets_two_dissectors_share_one_id_space() -> None:
    """A hub's new_stream allocates the ids: two sources in one run never collide."""
    ids = itertools.count(7)
    made: list[Stream] = []

    def new_stream(transport: Transport, client: str, server: str) -> Stream:
        made.append(Stream(next(ids), transport, client, server))
        return made[-1]

    one = Dissector(CaptureConfig(), new_stream=new_stream)
    two = Dissector(CaptureConfig(), new_stream=new_stream)
    a, b = conversation(40000), conversation(40001)
    got = feed(one, [(1.0, a.send(True, REQUEST))]) + feed(two, [(1.0, b.send(True, REQUEST))])
    assert [c.stream.id for c in got] == [7, 8]
    assert [c.stream for c in got] == made
    # the default numbering is the dissector's own, from 0
    assert feed(Dissector(CaptureConfig()), [(1.0, a.send(True, REQUEST))])[0].stream.id == 0


def test_capture_config_is_still_importable_from_pcapfile() -> None:
    from mbmon.sources import pcapfile

    assert pcapfile.CaptureConfig is CaptureConfig


# --------------------------------------------------------------------------- state


def test_closed_connections_release_their_state_at_once() -> None:
    conv = conversation()
    d = Dissector(CaptureConfig())
    packets = [(1.0, f) for f in conv.open()]
    packets += [(1.1, conv.send(True, REQUEST)), (1.2, conv.send(False, RESPONSE))]
    packets += [(1.3, f) for f in conv.close()]
    out = feed(d, packets)
    assert kinds(out)[-1] == "disconnect"
    assert d.stats()["open_connections"] == 0
    # a straggler (the last ACK retransmitted) is not taken for a new connection
    out = feed(d, [(5.0, conv.ack(True))])
    assert out == [] and d.stats()["streams"] == 1
    # after the linger even the addresses are forgotten
    assert d.tick(1.3 + CLOSED_LINGER) == []
    assert d.tcp == {} and d.next_deadline() is not None  # the idle scan is still scheduled


def test_reset_releases_state_too() -> None:
    conv = conversation()
    d = Dissector(CaptureConfig())
    feed(d, [(1.0, f) for f in conv.open()] + [(1.1, conv.reset(True))])
    assert d.stats()["open_connections"] == 0


def test_idle_connection_expires_through_tick_and_releases_held_bytes_first() -> None:
    conv = conversation()
    d = Dissector(CaptureConfig(), idle_timeout=10.0, hole_timeout=None)
    feed(d, [(1.0, f) for f in conv.open()])
    conv.client_next += 4  # 4 bytes lost: the request is held behind the hole
    assert feed(d, [(2.0, conv.send(True, REQUEST))]) == []
    assert d.tick(11.9) == []
    out = d.tick(13.0)  # idle scans run at most once a second
    assert kinds(out) == ["gap", f"chunk@2.0:{REQUEST.hex()}", "disconnect"]
    gap, _, bye = out
    assert isinstance(gap, Event) and gap.info["reason"] == "idle"
    assert isinstance(bye, Event) and bye.info["how"] == "idle" and "10 s" in bye.info["reason"]
    assert bye.ts == 12.0  # the moment it expired, not when the tick came
    assert d.stats()["open_connections"] == 0 and d.stats()["expired"] == 1
    # the same addresses later: a new stream (picked up mid-connection)
    out = feed(d, [(20.0, conv.send(True, REQUEST))])
    assert out[0].stream.id == 1


def test_busy_connection_does_not_expire() -> None:
    conv = conversation()
    d = Dissector(CaptureConfig(), idle_timeout=10.0)
    packets = [(1.0, f) for f in conv.open()]
    packets += [(1.0 + 5 * i, conv.send(True, REQUEST)) for i in range(10)]
    out = feed(d, packets)
    assert [i.kind for i in out if isinstance(i, Event)] == [EventKind.CONNECT]


def test_udp_pairs_expire_when_idle() -> None:
    d = Dissector(CaptureConfig(), idle_timeout=10.0)
    frame = pw.udp_frame(ETH, "10.0.0.2", "10.0.0.1", 40000, 502, REQUEST)
    first = d.packet_bytes(1.0, ETH, frame)
    out = d.tick(11.0)
    assert [(i.kind, i.info["how"], i.ts) for i in out] == [(EventKind.DISCONNECT, "idle", 11.0)]
    assert d.udp == {}
    again = d.packet_bytes(12.0, ETH, frame)
    assert again[0].stream.id == first[0].stream.id + 1


def test_rtu_buses_expire_when_idle_and_keep_their_names() -> None:
    d = Dissector(CaptureConfig(), "bus", idle_timeout=10.0)
    out: list[Chunk | Event] = []
    for iface in (0, 1):
        d.packet(1.0, pw.LINKTYPE_USER0, iface, b"\x01\x03", 0, 2, out)
    assert [(c.stream.id, c.stream.client) for c in out] == [(0, "bus"), (1, "bus#1")]
    bye = d.tick(11.0)
    assert [(e.kind, e.info["how"]) for e in bye] == [(EventKind.DISCONNECT, "idle")] * 2
    again: list[Chunk | Event] = []
    d.packet(12.0, pw.LINKTYPE_USER0, 1, b"\x01", 0, 1, again)
    assert [(c.stream.id, c.stream.client) for c in again] == [(2, "bus#1")]


def test_open_connections_are_bounded_by_max_flows() -> None:
    d = Dissector(CaptureConfig(), max_flows=64)
    out: list[Chunk | Event] = []
    for port in range(1000, 1300):
        conv = conversation(port)
        out += feed(d, [(float(port), conv.segment(True, pw.SYN))])
        out += feed(d, [(float(port), conv.send(True, REQUEST))])
    assert d.stats()["open_connections"] <= 64
    bye = [i for i in out if isinstance(i, Event) and i.kind is EventKind.DISCONNECT]
    assert len(bye) == 300 - d.stats()["open_connections"]
    # the least recently active went first
    assert [e.stream.client for e in bye[:3]] == [f"10.0.0.2:{p}" for p in (1000, 1001, 1002)]


MANY = textwrap.dedent(
    """
    import resource, struct, sys
    from mbmon.protocol.mbap import encode_adu
    from mbmon.sources.dissect import CaptureConfig, Dissector, MAX_CLOSED, MAX_FLOWS
    from mbmon.io.pcap import TcpConversation

    n, kind = int(sys.argv[1]), sys.argv[2]
    conv = TcpConversation("10.1.0.2:40000", "10.0.0.1:502")
    syn = conv.segment(True, 0x02)  # SYN
    conv.server_next = conv.server_isn + 1
    # the request with the client's FIN, the response with the server's FIN
    req = conv.segment(True, 0x19, encode_adu(1, 1, bytes.fromhex("0300000001")))
    resp = conv.segment(False, 0x19, encode_adu(1, 1, bytes.fromhex("03020007")))
    if kind == "short":
        order = [(syn, True), (req, True), (resp, False)]
    else:  # half-open: SYN and a request, never closed
        order = [(syn, True), (conv.segment(True, 0x18, req[54:]), True)]
    d = Dissector(CaptureConfig())
    packet, out, pack_into = d.packet, [], struct.pack_into
    ts, peaks = 0.0, []
    for i in range(n):
        ip, port = 0x0A010000 + i // 50000, 1024 + i % 50000
        ts += 0.001
        for frame, from_client in order:
            b = bytearray(frame)
            if from_client:
                pack_into("!I", b, 26, ip)
                pack_into("!H", b, 34, port)
            else:
                pack_into("!I", b, 30, ip)
                pack_into("!H", b, 36, port)
            packet(ts, 1, 0, bytes(b), 0, len(b), out)
        out.clear()
        if i + 1 in (n // 10, n):
            peaks.append(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
            assert d.stats()["open_connections"] <= MAX_FLOWS
            assert len(d.tcp) <= 2 * (MAX_FLOWS + MAX_CLOSED + 1)
    stats = d.stats()
    print(peaks[0], peaks[1], stats["streams"], stats["open_connections"], len(d.tcp))
    """
)


def test_a_million_connections_keep_memory_flat() -> None:
    """A million short connections (SYN, request + FIN, response + FIN) and 200,000
    half-open ones (SYN + request, never closed; twenty times the open-connection
    bound, so the bound works all along), each through one dissector: the peak RSS
    after all of them is the peak after the first tenth (a million of either once
    peaked at 2.7 GB and 2.0 GB). Two children, run side by side."""
    sizes = {"short": 1_000_000, "half-open": 200_000}
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}
    children = {
        kind: subprocess.Popen(
            [sys.executable, "-c", MANY, str(n), kind],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for kind, n in sizes.items()
    }
    for kind, child in children.items():
        stdout, stderr = child.communicate(timeout=1800)
        assert child.returncode == 0, stderr[-2000:]
        tenth, full, streams, _, _ = map(int, stdout.split())
        n = sizes[kind]
        assert streams == n, kind
        growth_mb = (full - tenth) / 1024
        assert growth_mb < 16, (
            f"{kind}: peak RSS {tenth / 1024:.0f} MB after {n // 10:,}, "
            f"{full / 1024:.0f} MB after {n:,}"
        )


# --------------------------------------------------------------------------- time


def test_a_hole_is_given_up_after_hole_timeout_without_further_packets() -> None:
    conv = conversation()
    d = Dissector(CaptureConfig(), hole_timeout=2.0)
    feed(d, [(1.0, f) for f in conv.open()])
    conv.client_next += 4  # a lost segment
    assert feed(d, [(10.0, conv.send(True, REQUEST))]) == []
    assert d.next_deadline() == 12.0
    assert d.tick(11.99) == []
    out = d.tick(12.0)
    assert kinds(out) == ["gap", f"chunk@10.0:{REQUEST.hex()}"]
    gap = out[0]
    assert isinstance(gap, Event)
    assert (gap.ts, gap.info) == (12.0, {"direction": "c2s", "bytes": 4, "reason": "timeout"})
    assert d.stats()["hole_timeouts"] == 1
    assert d.next_deadline() != 12.0


def test_a_hole_filled_in_time_is_no_gap() -> None:
    conv = conversation()
    d = Dissector(CaptureConfig(), hole_timeout=2.0)
    feed(d, [(1.0, f) for f in conv.open()])
    lost = conv.send(True, REQUEST[:4])
    out = feed(d, [(10.0, conv.send(True, REQUEST[4:])), (11.0, lost)])
    assert kinds(out) == [f"chunk@11.0:{REQUEST[:4].hex()}", f"chunk@10.0:{REQUEST[4:].hex()}"]
    assert d.tick(20.0) == []


def test_hole_timeout_also_runs_on_packet_time() -> None:
    """Packets move time on: the hole is given up before a later packet is handled."""
    conv, other = conversation(40000), conversation(40001)
    d = Dissector(CaptureConfig(), hole_timeout=2.0)
    feed(d, [(1.0, f) for f in conv.open()])
    conv.client_next += 4
    feed(d, [(10.0, conv.send(True, REQUEST))])
    out = feed(d, [(13.0, other.send(True, REQUEST))])
    assert kinds(out) == [
        "gap",
        f"chunk@10.0:{REQUEST.hex()}",
        f"chunk@13.0:{REQUEST.hex()}",
    ]


# --------------------------------------------------------------------------- times after a hole


def _records(path: Path, timeout: float = 1.0) -> list[object]:
    pipeline = Pipeline(None, PipelineConfig(timeout=timeout))
    records = []
    for item in read_capture(path):
        records += pipeline.feed(item)
    return records + pipeline.finish()


def test_response_behind_a_hole_keeps_its_own_time_and_latency(tmp_path: Path) -> None:
    """Request at 10.0, response at 10.2 behind a lost server segment,
    the hole given up at 15.0 (the client's ACK passes it): the response is stamped
    10.2, latency 200 ms (was 15.0 and 5 s; or 0.0 ms when both waited)."""
    conv = conversation()
    path = tmp_path / "hole.pcap"
    with PcapWriter(path) as w:
        for f in conv.open():
            w.write(9.0, f)
        w.write(10.0, conv.send(True, REQUEST))
        conv.server_next += 6  # six server bytes the capture lost
        w.write(10.2, conv.send(False, RESPONSE))
        w.write(15.0, conv.ack(True))  # acknowledges the lost bytes and the response
    records = _records(path)
    frames = [r for r in records if r.frame is not None]
    assert [(r.frame.direction, r.ts) for r in frames] == [
        (Direction.C2S, 10.0),
        (Direction.S2C, 10.2),
    ]
    assert frames[1].latency == pytest.approx(0.2)


def test_response_behind_a_hole_filled_later_keeps_the_time_of_its_last_byte(
    tmp_path: Path,
) -> None:
    """The response's first bytes arrive late (retransmitted at 15.0), its last
    bytes at 10.2: the ADU is stamped with its last byte's segment, 10.2."""
    conv = conversation()
    path = tmp_path / "filled.pcap"
    with PcapWriter(path) as w:
        for f in conv.open():
            w.write(9.0, f)
        w.write(10.0, conv.send(True, REQUEST))
        first = conv.send(False, RESPONSE[:5])  # lost on the first try
        w.write(10.2, conv.send(False, RESPONSE[5:]))
        w.write(15.0, first)  # the retransmission fills the hole
    # a timeout longer than the retransmission: the pairer must not give up first
    frames = [r for r in _records(path, timeout=10.0) if r.frame is not None]
    assert [r.ts for r in frames] == [10.0, 10.2]
    assert frames[1].latency == pytest.approx(0.2)


# --------------------------------------------------------------------------- busiest ports


def test_busiest_non_modbus_ports_are_counted() -> None:
    d = Dissector(CaptureConfig())
    packets = []
    for i in range(30):  # tcp/1502 both ways, many clients
        c = TcpConversation(f"10.0.0.{2 + i % 5}:{50000 + i}", "10.0.0.1:1502")
        packets += [c.send(True, REQUEST), c.send(False, RESPONSE)]
    packets += [pw.udp_frame(ETH, "10.0.0.2", "10.0.0.9", 40000, 161, b"x")] * 7
    c = TcpConversation("10.0.0.2:40000", "10.0.0.1:80")
    packets += [c.send(True, b"GET /")] * 3
    for f in packets:
        d.packet_bytes(1.0, ETH, f)
    assert d.busiest_ports(3) == [("tcp", 1502, 60), ("udp", 161, 7), ("tcp", 80, 3)]
    assert d.stats()["non_modbus"] == 70


def test_the_port_counter_is_bounded() -> None:
    from mbmon.sources.dissect import MAX_PORTS

    d = Dissector(CaptureConfig())
    for port in range(1000, 1000 + MAX_PORTS + 99):  # 502 is no other port
        d.packet_bytes(1.0, ETH, pw.udp_frame(ETH, "10.0.0.2", "10.0.0.9", 65000, port, b"x"))
    assert len(d._ports) == MAX_PORTS
    assert d.other_ports_dropped == 99


def test_read_capture_stats_carry_the_busiest_ports(tmp_path: Path) -> None:
    c = TcpConversation("10.0.0.2:50000", "10.0.0.1:1502")
    path = tmp_path / "elsewhere.pcap"
    with PcapWriter(path) as w:
        for f in [*c.open(), c.send(True, REQUEST), c.send(False, RESPONSE)]:
            w.write(1.0, f)
    stats: dict[str, object] = {}
    assert list(read_capture(path, stats=stats)) == []
    assert stats["busiest_ports"] == [("tcp", 1502, 5)]


def test_the_dissector_imports_no_capture_library() -> None:
    """Live capture uses scapy as a byte source only; the dissector never needs it."""
    code = (
        "import sys, mbmon.sources.dissect; "
        "print(','.join(m for m in ('scapy', 'serial', 'pymodbus') if m in sys.modules))"
    )
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0 and out.stdout.strip() == "", out.stderr
