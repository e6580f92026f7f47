"""Real records for the sink and log tests: byte sessions through the real pipeline (no mocks).

Imported as ``sink_records`` by tests/sinks and tests/io (a unique module name:
two ``conftest`` modules cannot both be imported by name).

The MBAP bytes are the manual's examples (§5.5.2.2, §5.5.2.7) and Modbus spec
frames; the RTU bus carries one good ADU and one with a broken CRC; a garbage
MBAP header makes noise. ``hrss_records`` runs the HRSS capture shipped in
``captures/`` through the HRSS profile (robot state and commands).
"""

from __future__ import annotations

import struct
from pathlib import Path

from mbmon.format import View
from mbmon.model import Chunk, Direction, Event, EventKind, Record, Stream, Transport
from mbmon.pipeline import Pipeline
from mbmon.protocol.crc import add_crc
from mbmon.sinks.base import SinkContext

REPO = Path(__file__).resolve().parents[2]
T0 = 1_700_000_000.25

TCP = Stream(0, Transport.TCP, "192.168.0.20:49152", "192.168.0.10:502")
RTU = Stream(1, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0")


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def session_items() -> list[Chunk | Event]:
    """A TCP session (connect, reads, writes, an exception, pipelining, a split ADU,
    garbage, disconnect) and an RTU bus with a good frame and a CRC error."""
    c2s, s2c = Direction.C2S, Direction.S2C
    items: list[Chunk | Event] = [Event(T0, TCP, EventKind.CONNECT)]
    t = T0
    frames = [
        (c2s, mbap(1, 1, bytes.fromhex("02012C0005"))),  # manual §5.5.2.2 query
        (s2c, mbap(1, 1, bytes.fromhex("020113"))),  # its response
        (c2s, mbap(2, 1, bytes.fromhex("1000C9000306006F00DE014D"))),  # manual §5.5.2.7
        (s2c, mbap(2, 1, bytes.fromhex("1000C90003"))),
        (c2s, mbap(3, 1, bytes.fromhex("0300C80002"))),
        (s2c, mbap(3, 1, bytes.fromhex("8302"))),  # exception 02
    ]
    for direction, data in frames:
        t += 0.01
        items.append(Chunk(t, TCP, direction, data))
    # two requests in one segment, their responses split inside the MBAP header
    t += 0.01
    two = mbap(4, 1, bytes.fromhex("0400640002")) + mbap(5, 2, bytes.fromhex("0100000008"))
    items.append(Chunk(t, TCP, c2s, two))
    answers = mbap(4, 1, bytes.fromhex("040400640065")) + mbap(5, 2, bytes.fromhex("010155"))
    t += 0.01
    items.append(Chunk(t, TCP, s2c, answers[:4]))
    t += 0.001
    items.append(Chunk(t, TCP, s2c, answers[4:]))
    t += 0.01
    garbage = bytes.fromhex("000912340006010300000001")  # protocol id 0x1234: noise
    items.append(Chunk(t, TCP, c2s, garbage))
    t += 0.01
    items.append(Chunk(t, TCP, c2s, mbap(6, 1, bytes.fromhex("0600C80001"))))
    t += 0.01
    items.append(Chunk(t, TCP, s2c, mbap(6, 1, bytes.fromhex("0600C80001"))))
    t += 0.5
    items.append(Event(t, TCP, EventKind.DISCONNECT, {"how": "fin", "by": "client"}))
    # RTU bus: a good request/response, then a response with a broken CRC
    good_req = add_crc(bytes.fromhex("010300000002"))
    good_resp = add_crc(bytes.fromhex("01030400010002"))
    bad = bytearray(add_crc(bytes.fromhex("0103000A0001")))
    bad[-1] ^= 0xFF
    for data in (good_req, good_resp, bytes(bad)):
        t += 0.02
        items.append(Chunk(t, RTU, Direction.BUS, data))
    return items


def run_pipeline(items: list[Chunk | Event], annotator: object = None) -> list[Chunk | Record]:
    """Chunks and the records they produce, interleaved as ``mbmon read`` hands them to sinks."""
    out: list[Chunk | Record] = []
    pipeline = Pipeline(annotator)  # type: ignore[arg-type]
    for item in items:
        if isinstance(item, Chunk):
            out.append(item)
        out.extend(pipeline.feed(item))
    out.extend(pipeline.finish())
    return out


def hrss_context(robot: str | None = None) -> SinkContext:
    from mbmon.semantics.profile import builtin_profile_text

    return SinkContext(
        view=View(robot=robot),
        command_line=["mbmon", "read", "captures/hrss_ptp.pcap", "--profile", "hrss"],
        source="captures/hrss_ptp.pcap",
        profiles=[("hrss", builtin_profile_text("hrss"))],
        profile_specs=["hrss"],
    )


def feed(sink: object, stream: list[Chunk | Record]) -> None:
    """Hand ``stream`` to ``sink`` as the hub does: only the hooks it has; a source
    event (an event record) also reaches ``on_event``."""
    on_chunk = getattr(sink, "on_chunk", None)
    on_event = getattr(sink, "on_event", None)
    on_record = getattr(sink, "on_record", None)
    for item in stream:
        if isinstance(item, Chunk):
            if on_chunk is not None:
                on_chunk(item)
            continue
        if on_event is not None and item.event is not None:
            on_event(item.event)
        if on_record is not None:
            on_record(item)
