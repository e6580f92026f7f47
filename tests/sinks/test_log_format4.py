"""Log format 4's rule, case by case, through the real pipeline and the MCAP sink: a
chunk that is exactly the ADU of the frame written right after it loses its
/modbus/raw message and that frame's message ends with the marker (exact bytes); every
other chunk keeps its message. And the log does not depend on where the sink's batches
are cut (batch sizes 1, 2, 3, 128, a move after every item)."""

from __future__ import annotations

import base64
import dataclasses
import struct
from pathlib import Path

from format4 import MARKS, as_format3
from sink_records import TCP, mbap, run_pipeline, session_items

from mbmon.format import View
from mbmon.io.mcap.layout import CHUNK_MARKS, chunk_marker
from mbmon.io.mcap.proto import decode_raw
from mbmon.io.mcap.reader import McapLog
from mbmon.io.replay import raw_items
from mbmon.model import Chunk, Direction, Event, EventKind, Record, Stream, Transport
from mbmon.sinks.base import SinkContext
from mbmon.sinks.mcap import McapSink

T0 = 1_700_000_000.25
C2S, S2C = Direction.C2S, Direction.S2C
READ = bytes.fromhex("0300000002")  # read 2 holding registers from 0
ANSWER = bytes.fromhex("030400010002")
CTX = SinkContext(view=View(), source="x.pcap")


def write(tmp: Path, items: list[Chunk | Event], **kw: object) -> list[tuple[str, int, bytes]]:
    """``items`` through the pipeline into a log; its messages (topic, log time, data)
    in file order."""
    path = tmp / "x.mcap"
    with McapSink(path, CTX, **kw) as sink:  # type: ignore[arg-type]
        for item in run_pipeline(items):
            if isinstance(item, Chunk):
                sink.on_chunk(item)
            else:
                sink.on_record(item)
    with McapLog(path) as log:
        return [(m.topic, m.log_time, m.raw) for m in log.messages()]


def stored_chunks(messages: list[tuple[str, int, bytes]]) -> list[bytes]:
    """The data of the chunk messages the log holds on /modbus/raw."""
    out = []
    for topic, _, data in messages:
        if topic == "/modbus/raw":
            obj = decode_raw(data)
            if obj["type"] == "chunk":
                out.append(data)
    return out


def marks(messages: list[tuple[str, int, bytes]]) -> list[bytes]:
    return [d[-6:] for t, _, d in messages if t == "/modbus/frames" and d[-6:] in MARKS]


def chunks(*parts: tuple[Direction, bytes], stream: Stream = TCP) -> list[Chunk | Event]:
    return [Chunk(T0 + 0.01 * i, stream, d, data) for i, (d, data) in enumerate(parts)]


def test_a_one_adu_chunk_is_left_out_and_its_frame_marked(tmp_path: Path) -> None:
    messages = write(tmp_path, chunks((C2S, mbap(1, 1, READ)), (S2C, mbap(1, 1, ANSWER))))
    assert stored_chunks(messages) == []
    assert marks(messages) == [b"\xaa\x01\x03c2s", b"\xaa\x01\x03s2c"]
    assert CHUNK_MARKS == {C2S: b"\xaa\x01\x03\x63\x32\x73", S2C: b"\xaa\x01\x03\x73\x32\x63"}
    frames = [d for t, _, d in messages if t == "/modbus/frames"]
    # the marker is the last thing in the message, after every other field
    assert all(f.endswith(m) for f, m in zip(frames, marks(messages), strict=True))
    # a reader gets the chunks back, exactly
    assert [d for t, _, d in as_format3(messages) if t == "/modbus/raw"] == [
        b'\n\x05chunk\x10\x00\x1a\x03tcp"\x12192.168.0.20:49152*\x10192.168.0.10:502:\x03c2s'
        + b"A"
        + _double(T0)
        + b"J\x0c"
        + mbap(1, 1, READ),
        b'\n\x05chunk\x10\x00\x1a\x03tcp"\x12192.168.0.20:49152*\x10192.168.0.10:502:\x03s2c'
        + b"A"
        + _double(T0 + 0.01)
        + b"J\x0d"
        + mbap(1, 1, ANSWER),
    ]


def _double(x: float) -> bytes:
    return struct.pack("<d", x)


def test_chunks_that_are_not_exactly_one_adu_keep_their_message(tmp_path: Path) -> None:
    two = mbap(1, 1, READ) + mbap(2, 1, READ)
    split = mbap(3, 1, READ)
    cases = {
        "two ADUs in one chunk": chunks((C2S, two)),
        "an ADU split over two chunks": chunks((C2S, split[:5]), (C2S, split[5:])),
        "noise then an ADU": chunks((C2S, b"\xff\xff" + mbap(4, 1, READ))),
    }
    for what, items in cases.items():
        messages = write(tmp_path, items)
        want = [c.data for c in items if isinstance(c, Chunk)]
        assert [decode_raw(d)["data"] for d in stored_chunks(messages)] == [
            _b64(x) for x in want
        ], what
        assert marks(messages) == [], what


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def test_a_timeout_between_chunk_and_frame_keeps_the_message(tmp_path: Path) -> None:
    """The request at T0 goes unanswered; the next request's chunk comes after the
    timeout: the pipeline gives the timeout event first, then the frame."""
    items = chunks((C2S, mbap(1, 1, READ)))
    items.append(Chunk(T0 + 5.0, TCP, C2S, mbap(2, 1, READ)))
    stream = run_pipeline(items)
    after = stream[stream.index(items[1]) + 1]
    assert isinstance(after, Record) and after.event is not None
    assert after.event.kind is EventKind.TIMEOUT
    messages = write(tmp_path, items)
    assert [decode_raw(d)["data"] for d in stored_chunks(messages)] == [_b64(mbap(2, 1, READ))]
    assert marks(messages) == [b"\xaa\x01\x03c2s"]  # the first one's


def test_rtu_over_tcp_and_a_bus_keep_their_messages(tmp_path: Path) -> None:
    from mbmon.protocol.rtu import encode_rtu

    over = Stream(0, Transport.RTU_OVER_TCP, "10.0.0.1:4000", "10.0.0.2:502")
    bus = Stream(0, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0")
    adu = encode_rtu(1, READ)
    for items in (
        chunks((C2S, adu), stream=over),
        [Chunk(T0, bus, Direction.BUS, adu)],
    ):
        messages = write(tmp_path, items)
        assert len(stored_chunks(messages)) == 1
        assert marks(messages) == []
        assert sum(t == "/modbus/frames" for t, _, _ in messages) == 1


def test_a_chunk_at_the_end_of_the_run_is_written(tmp_path: Path) -> None:
    items = chunks((C2S, mbap(1, 1, READ)), (S2C, mbap(1, 1, ANSWER)[:4]))  # half an answer
    messages = write(tmp_path, items)
    assert [decode_raw(d)["data"] for d in stored_chunks(messages)] == [
        _b64(mbap(1, 1, ANSWER)[:4])
    ]
    assert marks(messages) == [b"\xaa\x01\x03c2s"]


def test_the_rule_case_by_case() -> None:
    """:func:`chunk_marker` itself, on the records the pipeline makes of a one-ADU chunk:
    each condition of the rule broken on its own."""
    chunk, record = run_pipeline(chunks((C2S, mbap(7, 3, READ))))[:2]  # (a timeout follows)
    assert isinstance(chunk, Chunk) and isinstance(record, Record)
    from mbmon.format import record_to_json

    obj = record_to_json(record, View())
    assert chunk_marker(chunk, record, obj) == b"\xaa\x01\x03c2s"
    untimed = dataclasses.replace(chunk.stream, timed=False)
    other = dataclasses.replace(chunk.stream, id=9)
    broken = {
        "a raw dump (no capture times)": dataclasses.replace(chunk, stream=untimed),
        "another stream": dataclasses.replace(chunk, stream=other),
        "the other direction": dataclasses.replace(chunk, direction=S2C),
        "a bus": dataclasses.replace(chunk, direction=Direction.BUS),
        "protocol id 1": dataclasses.replace(chunk, data=chunk.data[:3] + b"\x01" + chunk.data[4:]),
        "a wrong length field": dataclasses.replace(
            chunk, data=chunk.data[:5] + b"\x07" + chunk.data[6:]
        ),
        "another tid": dataclasses.replace(chunk, data=b"\x00\x08" + chunk.data[2:]),
        "another unit": dataclasses.replace(chunk, data=chunk.data[:6] + b"\x04" + chunk.data[7:]),
        "a byte more": dataclasses.replace(chunk, data=chunk.data + b"\x00"),
        "another time": dataclasses.replace(chunk, ts=chunk.ts + 1e-6),
    }
    for what, bad in broken.items():
        assert chunk_marker(bad, record, obj) is None, what
    for ts in (0.0, -1.0, 1e30, float("nan")):  # implausible: the core's native condition
        bad_chunk = dataclasses.replace(chunk, ts=ts)
        bad_record = dataclasses.replace(record, ts=ts)
        assert chunk_marker(bad_chunk, bad_record, {**obj, "time": ts}) is None, ts
    assert chunk_marker(chunk, record, {**obj, "tid": None}) is None
    assert chunk_marker(chunk, record, {**obj, "unit": "3"}) is None


def test_the_log_does_not_depend_on_where_batches_are_cut(tmp_path: Path) -> None:
    """The same capture with the sink's batch size 1, 2, 3 and 128, and with a move after
    every item: the same messages, in the same order (and chunks left out)."""
    items = session_items()
    logs = []
    for chunk_size in (1 << 12, 2 << 12, 3 << 12, 1 << 20):  # batches of 1, 2, 3, 128
        logs.append(write(tmp_path, items, chunk_size=chunk_size))
    path = tmp_path / "moved.mcap"
    with McapSink(path, CTX) as sink:
        for item in run_pipeline(items):
            if isinstance(item, Chunk):
                sink.on_chunk(item)
            else:
                sink.on_record(item)
            sink._move()  # a batch cut after every item, the chunk's too
    with McapLog(path) as log:
        logs.append([(m.topic, m.log_time, m.raw) for m in log.messages()])
    assert all(log == logs[0] for log in logs[1:])
    assert marks(logs[0]) and stored_chunks(logs[0])
    with McapLog(path) as log:  # every chunk comes back, in order
        got = [c for c in raw_items(log) if isinstance(c, Chunk)]
    assert got == [c for c in items if isinstance(c, Chunk)]
