"""Chunks and events written as a capture read back as the same chunks and events."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.io.pcap import ChunkWriter
from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.sources.pcapfile import CaptureConfig, read_capture

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "captures" / "real"
FILES = sorted(p.name for p in REAL.glob("*.pcap*")) if REAL.is_dir() else []


def normalised(items: Iterable[Chunk | Event]) -> list[tuple[object, ...]]:
    """Items with stream ids renumbered by first appearance, gap reasons dropped
    (why a gap was given up depends on what follows it) and ts to the microsecond."""
    ids: dict[int, int] = {}
    out: list[tuple[object, ...]] = []
    for item in items:
        sid = ids.setdefault(item.stream.id, len(ids)) if item.stream else None
        ts = round(item.ts * 1e6)
        if isinstance(item, Chunk):
            out.append((sid, item.stream.transport, item.direction, item.data, ts))
        else:
            info = tuple(sorted((k, v) for k, v in item.info.items() if k != "reason"))
            out.append((sid, item.kind, info, ts))
    return out


def round_trip(
    items: list[Chunk | Event], path: Path, pcapng: bool, **kw: object
) -> list[Chunk | Event]:
    with ChunkWriter(path, pcapng=pcapng) as writer:
        for item in items:
            writer.write(item)
    return list(read_capture(path, **kw))  # type: ignore[arg-type]


@pytest.mark.parametrize("pcapng", [False, True])
@pytest.mark.parametrize("name", FILES or ["<none>"])
def test_real_captures_survive_the_round_trip(tmp_path: Path, name: str, pcapng: bool) -> None:
    if not REAL.is_dir():
        pytest.skip(f"{REAL} absent (../shared/captures/real)")
    items = list(read_capture(REAL / name))
    again = round_trip(items, tmp_path / "out.cap", pcapng)
    want, got = normalised(items), normalised(again)
    # timestamps: equal to the microsecond (5View stores nanoseconds as a float)
    assert [w[:-1] for w in want] == [g[:-1] for g in got]
    assert all(abs(w[-1] - g[-1]) <= 1 for w, g in zip(want, got, strict=True))  # type: ignore[operator]


TCP = Stream(0, Transport.TCP, "10.0.0.1:40000", "10.0.0.2:502")
UDP = Stream(1, Transport.RTU_OVER_UDP, "[2001:db8::1]:40000", "[2001:db8::2]:4002")
BUS_A = Stream(2, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0")
BUS_B = Stream(3, Transport.RTU, "/dev/ttyUSB1", "/dev/ttyUSB1")
ODD = Stream(4, Transport.RTU_OVER_TCP, "proxy-client", "robot")

SCRIPT: list[Chunk | Event] = [
    Event(1.0, TCP, EventKind.CONNECT),
    Chunk(1.1, TCP, Direction.C2S, b"\x00\x01\x00\x00\x00\x06\x01\x03\x00\x00\x00\x01"),
    Chunk(1.2, UDP, Direction.C2S, bytes.fromhex("010300000001840a")),
    Chunk(1.3, BUS_A, Direction.BUS, bytes.fromhex("0103")),
    Event(1.4, TCP, EventKind.GAP, {"direction": "s2c", "bytes": 11}),
    Chunk(1.5, TCP, Direction.S2C, b"\x00\x02\x00\x00\x00\x05\x01\x03\x02\x00\x07"),
    Chunk(1.6, BUS_B, Direction.BUS, bytes.fromhex("02")),
    Chunk(1.7, UDP, Direction.S2C, bytes.fromhex("01030200077e46")),
    Chunk(1.8, ODD, Direction.C2S, bytes.fromhex("010300000001840a")),
    Event(1.9, TCP, EventKind.DISCONNECT, {"how": "rst", "by": "server"}),
    Event(2.0, ODD, EventKind.DISCONNECT, {"how": "fin", "by": "client", "half_closed": True}),
]


def test_every_transport_and_event_in_pcapng(tmp_path: Path) -> None:
    config = CaptureConfig(tcp_ports=frozenset({502}), rtu_ports=frozenset({4002}))
    again = round_trip(SCRIPT, tmp_path / "x.pcapng", True, config=config)
    want = normalised(SCRIPT)
    got = normalised(again)
    # the made-up endpoints of the odd stream use port 502: read back as MBAP
    want = [(*w[:1], Transport.TCP, *w[2:]) if w[0] == 4 and len(w) == 5 else w for w in want]
    assert got == want
    buses = {i.stream.client for i in again if i.stream and i.stream.transport is Transport.RTU}
    assert buses == {"x.pcapng", "x.pcapng#2"}  # one interface per bus


def test_pcap_holds_one_link_type(tmp_path: Path) -> None:
    with ChunkWriter(tmp_path / "x.pcap") as writer:
        writer.write(SCRIPT[1])
        with pytest.raises(ValueError, match="needs pcapng"):
            writer.write(SCRIPT[3])
    bus_only = round_trip([SCRIPT[3], SCRIPT[6]], tmp_path / "bus.pcap", False)
    assert [c.data for c in bus_only if isinstance(c, Chunk)] == [b"\x01\x03", b"\x02"]


def test_nothing_written_is_a_valid_empty_capture(tmp_path: Path) -> None:
    with ChunkWriter(tmp_path / "x.pcap"):
        pass
    assert list(read_capture(tmp_path / "x.pcap")) == []


@settings(max_examples=80, deadline=None)
@given(
    st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.sampled_from([1e17, 1.8e19, 1.7e12, -1e12, 4294967296.0, 2.0**64]),
    ),
    st.booleans(),
)
def test_fuzz_any_time_is_written_or_counted(ts: float, pcapng: bool) -> None:
    """A time the file cannot hold never raises (it was struct.error):
    the packet is written at the previous packet's time and counted."""
    import dataclasses
    import io

    items = [dataclasses.replace(x, ts=ts) if k == 1 else x for k, x in enumerate(SCRIPT[:3])]
    out = io.BytesIO()
    writer = ChunkWriter(out, pcapng=pcapng)
    for item in items:
        if pcapng or item.stream is not UDP:
            writer.write(item)
    writer.close()
    limit = 1.8e10 if pcapng else 4294967295.0
    assert writer.bad_times == (0 if 0 <= ts < limit else 1)


def test_adu_segments_cover_every_byte_in_order(tmp_path: Path) -> None:
    """adu_segments: one ADU per segment, bytes that frame as no ADU in segments of
    their own; the bytes of each direction, read back, are the bytes written."""
    req = b"\x00\x01\x00\x00\x00\x06\x01\x03\x00\x00\x00\x01"
    resp = b"\x00\x01\x00\x00\x00\x05\x01\x03\x02\x00\x07"
    c2s = req[:3] + b"", req[3:] + req[:9], req[9:] + b"\xff\xfe junk", req
    items: list[Chunk | Event] = [Event(1.0, TCP, EventKind.CONNECT)]
    t = 1.0
    for part in c2s:
        t += 0.1
        items.append(Chunk(t, TCP, Direction.C2S, part))
    items.append(Chunk(t + 0.1, TCP, Direction.S2C, resp[:4]))
    items.append(Chunk(t + 0.2, TCP, Direction.S2C, resp[4:]))
    items.append(Event(t + 0.3, TCP, EventKind.DISCONNECT, {"how": "fin", "by": "client"}))
    path = tmp_path / "a.pcap"
    with ChunkWriter(path, adu_segments=True) as writer:
        for item in items:
            writer.write(item)
    again = [c for c in read_capture(path) if isinstance(c, Chunk)]
    sent = b"".join(c.data for c in items if isinstance(c, Chunk) and c.direction is Direction.C2S)
    assert b"".join(c.data for c in again if c.direction is Direction.C2S) == sent
    assert [c.data for c in again if c.direction is Direction.S2C] == [resp]
    assert [round(c.ts, 6) for c in again if c.direction is Direction.S2C] == [round(t + 0.2, 6)]
    c2s_segments = [c.data for c in again if c.direction is Direction.C2S]
    assert c2s_segments[:2] == [req, req]  # each ADU whole, at its last byte's time
    assert req in c2s_segments[2:]


def test_idle_expiry_writes_no_packets(tmp_path: Path) -> None:
    """The dissector giving up on a quiet connection is not a close on the wire:
    the written capture must not show a FIN exchange that never happened."""
    idle = Event(400.0, TCP, EventKind.DISCONNECT, {"how": "idle", "reason": "no packet for 300 s"})
    with_idle = tmp_path / "idle.pcap"
    without = tmp_path / "plain.pcap"
    for path, items in ((with_idle, [*SCRIPT[:2], idle]), (without, SCRIPT[:2])):
        with ChunkWriter(path) as writer:
            for item in items:
                writer.write(item)
    assert with_idle.read_bytes() == without.read_bytes()
