"""The MCAP sink: topics, schemas, times, metadata, crash safety (read back with `mcap`)."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import jsonschema
import pytest
from format4 import MARKS, as_format3, left_out
from mcap.reader import NonSeekingReader, make_reader
from sink_records import REPO, feed, hrss_context

from mbmon import __version__
from mbmon.format import View, record_line, record_to_json
from mbmon.io.mcap.layout import PROTO_TOPICS, full_frame_object, slim_frame_object
from mbmon.io.mcap.proto import decode_payload, descriptor_set, encode_frame
from mbmon.io.mcap.reader import McapLog
from mbmon.io.replay import logged_records
from mbmon.model import Chunk, Record, RecordKind
from mbmon.sinks.base import SinkContext, open_sink
from mbmon.sinks.mcap import TOPIC_SCHEMAS, McapSink, schema_text

CTX = SinkContext(
    view=View(), command_line=["mbmon", "read", "x.pcap", "-w", "x.mcap"], source="x.pcap"
)


def write_log(path: Path, stream: list[Chunk | Record], ctx: SinkContext = CTX) -> Path:
    with open_sink(path, ctx) as sink:
        assert isinstance(sink, McapSink)
        feed(sink, stream)
    return path


def messages(path: Path) -> list[tuple[str, str, object, int, int]]:
    """(topic, JSON schema name, decoded object, log_time, publish_time) via the mcap
    package: a protobuf message (format 3) decoded to the object format 2 stored, with
    the JSON schema that object follows."""
    out = []
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            assert schema is not None
            if channel.topic in PROTO_TOPICS:
                assert channel.message_encoding == schema.encoding == "protobuf"
                assert schema.name == PROTO_TOPICS[channel.topic]
            else:
                assert channel.message_encoding == "json"
            obj = decode_payload(schema.name, channel.message_encoding, msg.data)
            name = TOPIC_SCHEMAS[channel.topic]
            out.append((channel.topic, name, obj, msg.log_time, msg.publish_time))
    return out


def records_of(stream: list[Chunk | Record]) -> list[Record]:
    return [x for x in stream if isinstance(x, Record)]


def ns(ts: float) -> int:
    return round(ts * 1_000_000) * 1000


def test_topics_schemas_and_summary(tmp_path: Path, session_stream: list) -> None:
    path = write_log(tmp_path / "s.mcap", session_stream)
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        topics = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        # written without a profile: no (empty) /hrss channels
        assert set(topics) == set(TOPIC_SCHEMAS) - {"/hrss/state", "/hrss/commands"}
        for topic, schema in topics.items():
            if topic in PROTO_TOPICS:  # format 3: protobuf, with its FileDescriptorSet
                assert schema.name == PROTO_TOPICS[topic]
                assert schema.encoding == "protobuf"
                assert schema.data == descriptor_set()
                continue
            assert schema.name == TOPIC_SCHEMAS[topic]
            assert schema.encoding == "jsonschema"
            assert schema.data == schema_text(schema.name)
        assert topics["/modbus/monitor"].name == "foxglove.Log"
        assert summary.chunk_indexes, "messages must be in chunks"
        assert {ci.compression for ci in summary.chunk_indexes} == {"zstd"}
        counts = summary.statistics.channel_message_counts
        by_topic = {ch.topic: counts.get(ch.id, 0) for ch in summary.channels.values()}
    recs = records_of(session_stream)
    chunks = [x for x in session_stream if isinstance(x, Chunk)]
    assert by_topic["/modbus/monitor"] == len(recs)
    with McapLog(path) as log:  # format 4: a one-ADU chunk's message is left out
        marked = left_out([(m.topic, m.log_time, m.raw) for m in log.messages()])
    assert 0 < marked < len(chunks)
    assert by_topic["/modbus/raw"] == len(chunks) - marked + 2  # plus connect and disconnect
    frames = [r for r in recs if r.kind is not RecordKind.EVENT]
    assert by_topic["/modbus/frames"] == len(frames)
    # the non-seeking reader (a pipe) sees the same file
    with open(path, "rb") as f:
        n = sum(1 for _ in NonSeekingReader(f, validate_crcs=True).iter_messages())
    assert n == sum(by_topic.values())


@pytest.mark.parametrize("which", ["session", "hrss"])
def test_every_message_validates_against_its_schema(
    tmp_path: Path, which: str, session_stream: list, hrss_stream: list
) -> None:
    stream = session_stream if which == "session" else hrss_stream
    ctx = CTX if which == "session" else hrss_context(robot="127.0.0.1:502")
    path = write_log(tmp_path / "v.mcap", stream, ctx)
    validators = {}
    for name in set(TOPIC_SCHEMAS.values()):
        schema = json.loads(schema_text(name))
        cls = jsonschema.validators.validator_for(schema, default=jsonschema.Draft202012Validator)
        cls.check_schema(schema)
        validators[name] = cls(schema)
    seen: dict[str, int] = {}
    for topic, schema_name, data, _, _ in messages(path):
        validators[schema_name].validate(data)
        seen[topic] = seen.get(topic, 0) + 1
    expected = {"/modbus/raw", "/modbus/frames", "/modbus/monitor", "/mbmon/events"}
    if which == "hrss":
        expected |= {"/hrss/state", "/hrss/commands"}
    assert expected <= set(seen)


def test_schemas_reject_wrong_messages() -> None:
    """The schemas are strict enough to catch drift (so the validation test can fail)."""
    frame = json.loads(schema_text("modbus.Frame.v1"))
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"index": 0, "time": 1.0}, frame)  # keys missing
    frame2 = json.loads(schema_text("modbus.Frame.v2"))  # format 2: null members left out
    jsonschema.validate({"index": 0, "kind": "request", "fc": 3}, frame2)
    for bad in ({"index": 0, "time": 1.0}, {"index": 0, "kind": "request", "fc": "3"}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, frame2)
    log = json.loads(schema_text("foxglove.Log"))
    good = {
        "timestamp": {"sec": 1, "nsec": 2},
        "level": 2,
        "message": "m",
        "name": "n",
        "file": "f",
        "line": 0,
    }
    jsonschema.validate(good, log)
    for bad in ({**good, "level": 7}, {**good, "line": -1}, {**good, "timestamp": {"sec": 1.5}}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, log)


# Foxglove's well-known Log schema (foxglove-sdk schemas/jsonschema/Log.json): field -> JSON type.
FOXGLOVE_LOG = {
    "timestamp": "object",
    "level": None,  # foxglove.LogLevel: UNKNOWN 0, DEBUG 1, INFO 2, WARNING 3, ERROR 4, FATAL 5
    "message": "string",
    "name": "string",
    "file": "string",
    "line": "integer",
}


def test_foxglove_log_schema_is_foxglove_s() -> None:
    schema = json.loads(schema_text("foxglove.Log"))
    assert schema["title"] == "foxglove.Log"
    props = schema["properties"]
    assert set(props) == set(FOXGLOVE_LOG)
    for name, kind in FOXGLOVE_LOG.items():
        if kind is not None:
            assert props[name]["type"] == kind, name
    assert set(props["timestamp"]["properties"]) == {"sec", "nsec"}
    assert props["timestamp"]["properties"]["sec"]["type"] == "integer"
    assert props["timestamp"]["properties"]["nsec"]["maximum"] == 999_999_999
    levels = {item["title"]: item["const"] for item in props["level"]["oneOf"]}
    assert levels == {"UNKNOWN": 0, "DEBUG": 1, "INFO": 2, "WARNING": 3, "ERROR": 4, "FATAL": 5}
    assert sorted(schema["required"]) == sorted(FOXGLOVE_LOG)


def test_messages_carry_the_records(tmp_path: Path, session_stream: list) -> None:
    """/modbus/frames etc. hold exactly the read --json objects (frames: format 2's, without
    the line and the null members, which a reader puts back); monitor the console lines."""
    path = write_log(tmp_path / "r.mcap", session_stream)
    msgs = messages(path)
    recs = records_of(session_stream)
    view = View()
    frames = [d for t, _, d, _, _ in msgs if t == "/modbus/frames"]
    expect = [record_to_json(r, view) for r in recs if r.kind is not RecordKind.EVENT]
    marked = [f.pop("chunk") for f in frames if "chunk" in f]  # format 4's, not the record's
    assert marked and set(marked) <= {"c2s", "s2c"}
    assert frames == json.loads(json.dumps([slim_frame_object(o) for o in expect]))
    assert all("line" not in f and None not in f.values() for f in frames)
    lines = {d["line"]: d["message"] for t, _, d, _, _ in msgs if t == "/modbus/monitor"}
    full = [{**full_frame_object(f), "line": lines[f["index"]]} for f in frames]
    assert full == json.loads(json.dumps(expect))
    assert [list(f) for f in full] == [list(o) for o in expect]  # format 1's member order
    events = [d for t, _, d, _, _ in msgs if t == "/mbmon/events" and d["index"] is not None]
    kinds = [(d["kind"], d.get("event")) for d in events]
    assert kinds == [
        ("event", "connect"),
        ("noise", None),
        ("event", "disconnect"),
        ("noise", None),  # the RTU CRC error
    ]
    assert "CRC" in events[-1]["malformed"]
    monitor = [d for t, _, d, _, _ in msgs if t == "/modbus/monitor"]
    assert [m["message"] for m in monitor] == [record_line(r, view) for r in recs]
    assert [m["line"] for m in monitor] == [r.index for r in recs]
    assert [m["file"] for m in monitor] == [""] * len(recs)  # the source is the metadata's
    levels = {r.kind: m["level"] for r, m in zip(recs, monitor, strict=True)}
    assert levels[RecordKind.REQUEST] == 2
    assert levels[RecordKind.EXCEPTION] == 3
    assert levels[RecordKind.NOISE] == 4
    names = {m["name"] for m in monitor}
    assert "#0 192.168.0.20:49152 <> 192.168.0.10:502" in names
    assert "#1 /dev/ttyUSB0" in names


def test_times_are_capture_times_in_ns(tmp_path: Path, session_stream: list) -> None:
    path = write_log(tmp_path / "t.mcap", session_stream)
    msgs = messages(path)
    wall = time.time_ns()
    for topic, _, data, log_time, publish_time in msgs:
        assert log_time == publish_time
        assert abs(log_time - wall) > 10**15, "wall clock used instead of capture time"
        if topic == "/modbus/monitor":
            assert data["timestamp"]["sec"] * 10**9 + data["timestamp"]["nsec"] == log_time
        elif topic == "/modbus/raw":
            assert log_time == ns(data["ts"])
        elif data.get("index") is not None:
            assert log_time == ns(data["time"])
    raw = [d for t, _, d, _, _ in msgs if t == "/modbus/raw"]
    assert raw[0]["event"] == "connect"
    assert ns(raw[0]["ts"]) == 1_700_000_000_250_000_000


def test_raw_topic_is_lossless(tmp_path: Path, session_stream: list) -> None:
    path = write_log(tmp_path / "raw.mcap", session_stream)
    with McapLog(path) as log:  # format 4: the chunks left out rebuilt from their frames
        stored3 = as_format3([(m.topic, m.log_time, m.raw) for m in log.messages()])
    raw = [decode_payload("modbus.Raw", "protobuf", d) for t, _, d in stored3 if t == "/modbus/raw"]
    chunks = [x for x in session_stream if isinstance(x, Chunk)]
    stored = [d for d in raw if d["type"] == "chunk"]
    assert len(stored) == len(chunks)
    for d, c in zip(stored, chunks, strict=True):
        assert base64.b64decode(d["data"]) == c.data
        assert d["ts"] == c.ts
        assert d["direction"] == c.direction.value
        assert (d["stream"], d["transport"], d["client"], d["server"]) == (
            c.stream.id,
            c.stream.transport.value,
            c.stream.client,
            c.stream.server,
        )
    events = [d for d in raw if d["type"] == "event"]
    assert [e["event"] for e in events] == ["connect", "disconnect"]
    assert events[1]["info"] == {"how": "fin", "by": "client"}


def test_metadata_and_profile_attachments(tmp_path: Path, hrss_stream: list) -> None:
    ctx = hrss_context()
    path = write_log(tmp_path / "m.mcap", hrss_stream, ctx)
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = list(reader.iter_attachments())
    info = meta["mbmon"]
    assert info["version"] == __version__
    assert json.loads(info["command_line"]) == ctx.command_line
    assert info["source"] == "captures/hrss_ptp.pcap"
    assert json.loads(info["profiles"]) == ["hrss"]
    # the analysis settings as given in the context (not parsed from the command line)
    assert json.loads(info["profile_specs"]) == ["hrss"]
    assert json.loads(info["profile_bindings"]) == [["hrss", 0]]
    assert (json.loads(info["timeout"]), json.loads(info["baud"])) == (1.0, None)
    assert [(a.name, a.media_type) for a in attachments] == [("hrss.toml", "application/toml")]
    assert attachments[0].data.decode() == ctx.profiles[0][1]


def test_state_and_commands_topics(tmp_path: Path, hrss_stream: list) -> None:
    path = write_log(tmp_path / "h.mcap", hrss_stream, hrss_context())
    msgs = messages(path)
    recs = records_of(hrss_stream)
    states = [d for t, _, d, _, _ in msgs if t == "/hrss/state"]
    with_state = [r for r in recs if r.state is not None]
    assert len(states) == len(with_state) > 0
    for d, r in zip(states, with_state, strict=True):
        assert d["index"] == r.index
        assert {k: v for k, v in d.items() if k not in ("time", "index")} == dict(r.state or {})
    commands = [d for t, _, d, _, _ in msgs if t == "/hrss/commands"]
    assert [c["command"]["phase"] for c in commands] == ["written", "executing", "success"]
    assert commands[-1]["command"]["text"].startswith("PTP")


def test_non_finite_state_values_are_left_out(tmp_path: Path, hrss_stream: list) -> None:
    import dataclasses

    rec = next(r for r in records_of(hrss_stream) if r.state is not None)
    odd = dataclasses.replace(rec, state={"a1": float("nan"), "a2": 1.5, "x": float("inf")})
    path = write_log(tmp_path / "nan.mcap", [odd], hrss_context())
    states = [d for t, _, d, _, _ in messages(path) if t == "/hrss/state"]
    assert states == [{"time": rec.ts, "index": rec.index, "a2": 1.5}]


def test_closed_on_error_inside_with(tmp_path: Path, session_stream: list) -> None:
    path = tmp_path / "err.mcap"
    with pytest.raises(RuntimeError), open_sink(path, CTX) as sink:
        feed(sink, session_stream[:10])
        raise RuntimeError("boom")
    with McapLog(path) as log:
        assert log.finished
        assert sum(1 for _ in log.messages()) > 10


def test_small_chunks(tmp_path: Path, session_stream: list, hrss_stream: list) -> None:
    path = tmp_path / "small.mcap"
    with McapSink(path, CTX, chunk_size=300) as sink:
        feed(sink, session_stream)
        feed(sink, hrss_stream)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None and len(summary.chunk_indexes) > 20
    full = messages(path)
    assert len(full) == summary.statistics.message_count


def _unfinished_copy(src: Path, dst: Path) -> Path:
    shutil.copyfile(src, dst)
    return dst


def test_flushed_within_a_second_while_records_flow(tmp_path: Path, session_stream: list) -> None:
    path = tmp_path / "live.mcap"
    sink = McapSink(path, CTX)
    try:
        first = session_stream[: len(session_stream) // 2]
        feed(sink, first)
        time.sleep(0.6)
        feed(sink, session_stream[len(session_stream) // 2 : -1])  # one write triggers a flush
        time.sleep(1.0)  # the rest waits for the timer thread
        copy = _unfinished_copy(path, tmp_path / "copy.mcap")
    finally:
        sink.close()
    with McapLog(copy) as log:
        assert not log.finished
        got = [m.json() for m in log.messages(["/modbus/monitor"])]
        assert log.status.problem is None or "cut off" not in log.status.problem
    expected = [r for r in records_of(session_stream[:-1])]
    assert [m["line"] for m in got] == [r.index for r in expected]


def test_idle_flush_by_timer(tmp_path: Path, session_stream: list) -> None:
    """No more records after the first few: the timer thread still writes them out."""
    path = tmp_path / "idle.mcap"
    sink = McapSink(path, CTX)
    try:
        feed(sink, session_stream[:3])
        size_before = path.stat().st_size
        time.sleep(1.2)
        copy = _unfinished_copy(path, tmp_path / "copy.mcap")
    finally:
        sink.close()
    assert copy.stat().st_size > size_before
    with McapLog(copy) as log:
        topics = [m.topic for m in log.messages()]
    assert "/modbus/monitor" in topics and "/modbus/raw" in topics


_WRITER = r"""
import dataclasses, sys, time
sys.path.insert(0, sys.argv[2])
from sink_records import session_items, run_pipeline
from mbmon.format import View
from mbmon.model import Chunk
from mbmon.sinks.base import SinkContext
from mbmon.sinks.mcap import McapSink

base = [x for x in run_pipeline(session_items()) if not isinstance(x, Chunk)]
sink = McapSink(sys.argv[1], SinkContext(view=View(), source="loop"))
index, t = 0, 1_700_000_000.0
while True:
    for rec in base:
        t += 0.001
        sink.on_record(dataclasses.replace(rec, index=index, ts=t))
        sys.stdout.write(f"{index}\n")
        sys.stdout.flush()
        index += 1
    time.sleep(0.05)  # about 350 records/s: chunks never fill up by size in 2 s
"""


def test_sigkill_loses_at_most_the_last_second(tmp_path: Path) -> None:
    """A writer killed with SIGKILL: every record handed over >1 s before the kill is recovered."""
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(path), str(Path(__file__).parent)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    received: list[tuple[float, int]] = []

    def reader() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.endswith("\n"):  # the kill may cut the last line
                received.append((time.monotonic(), int(line)))

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not received and time.monotonic() < deadline:
        time.sleep(0.05)
    assert received, "the writer never started"
    time.sleep(2.0)
    killed_at = time.monotonic()
    proc.kill()
    proc.wait()
    thread.join(timeout=5)
    assert proc.stdout is not None
    proc.stdout.close()
    old = {i for t, i in received if t < killed_at - 1.0}
    assert len(old) > 100
    with McapLog(path) as log:
        assert not log.finished
        got = [m.json()["line"] for m in log.messages(["/modbus/monitor"])]
        status = log.status
    assert set(got) >= old, f"lost {len(old - set(got))} records older than 1 s"
    assert got == list(range(len(got))), "recovered records must be a prefix, in order"
    assert status.messages > 0 and status.describe().startswith("log was not finished")
    with McapLog(path) as log:  # format 3 on: each frame object gets its line back
        assert log.metadata["mbmon"]["format"] == "4"
        frames = [r for r in logged_records(log) if r.obj is not None and r.obj.get("fc")]
    assert len(frames) > 100
    assert all(r.obj is not None and r.obj["line"] == r.text != "" for r in frames)


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="/dev/full absent")
def test_full_disk_is_an_error_not_a_hang() -> None:
    with pytest.raises(OSError):
        McapSink("/dev/full", CTX)


ODD_TOML = """\
[profile]
name = "odd"

[[holding_registers]]
name = "SPEED"
address = 200
type = "u16"
label = 'speed "fast" \\ ° ","notes":["x'
"""


def test_frame_messages_match_the_slow_encoding(tmp_path: Path) -> None:
    """Frame records take a fast path (the read --json bytes, the line cut out of them):
    its frames bytes, monitor lines and levels equal what record_to_json, record_line and
    log_level give, also for a label with quotes, a backslash, non-ASCII text and a
    fake key, for unsolicited, malformed and exception frames and frames with "fields"."""
    from sink_records import T0, TCP, mbap, run_pipeline

    from mbmon.cli import make_annotator
    from mbmon.format import json_line
    from mbmon.model import Direction
    from mbmon.sinks.mcap import log_level

    profile = tmp_path / "odd.toml"
    profile.write_text(ODD_TOML, "utf-8")
    c2s, s2c = Direction.C2S, Direction.S2C
    frames = [
        (c2s, mbap(1, 1, bytes.fromhex("0300C80001"))),
        (s2c, mbap(1, 1, bytes.fromhex("0302002A"))),
        (s2c, mbap(77, 1, bytes.fromhex("0302002B"))),  # unsolicited
        (c2s, mbap(2, 1, bytes.fromhex("0300C8"))),  # malformed (truncated)
        (c2s, mbap(3, 1, bytes.fromhex("0600C80005"))),
        (s2c, mbap(3, 1, bytes.fromhex("8604"))),  # exception
        (c2s, mbap(4, 1, bytes.fromhex("170000000200C80001021234"))),  # with "fields"
        (s2c, mbap(4, 1, bytes.fromhex("170400010002"))),
        (c2s, mbap(5, 1, bytes.fromhex("2B0E0100"))),  # with "fields"
    ]
    items = [Chunk(T0 + 0.01 * i, TCP, d, data) for i, (d, data) in enumerate(frames)]
    stream = run_pipeline(items, make_annotator([str(profile)]))
    recs = records_of(stream)
    # the malformed request times out: an event, which takes the slow path
    kinds = ["request", "response", "response", "request", "request", "exception"]
    kinds += ["request", "response", "request", "event", "event"]
    assert [r.kind.value for r in recs] == kinds
    assert recs[3].frame is not None and recs[3].frame.pdu.malformed
    view = View(robot="192.168.0.10")
    ctx = SinkContext(view=view, source='odd "source" °.pcap')
    path = write_log(tmp_path / "odd.mcap", stream, ctx)
    raw_frames, monitor = [], []
    with open(path, "rb") as f:
        for _, channel, msg in make_reader(f, validate_crcs=True).iter_messages():
            if channel.topic == "/modbus/frames":
                raw_frames.append(msg.data)
            elif channel.topic == "/modbus/monitor":
                monitor.append(json.loads(msg.data))
    frame_recs = [r for r in recs if r.frame is not None]
    assert sum(f[-6:] in MARKS for f in raw_frames) > 0  # format 4: the rest as format 3
    raw_frames = [f[:-6] if f[-6:] in MARKS else f for f in raw_frames]
    assert raw_frames == [  # format 3: format 2's object as protobuf
        encode_frame(json.loads(json_line(slim_frame_object(record_to_json(r, view)))))
        for r in frame_recs
    ]
    assert [m["message"] for m in monitor] == [record_line(r, view) for r in recs]
    assert [m["level"] for m in monitor] == [log_level(r, record_to_json(r, view)) for r in recs]
    assert [m["level"] for m in monitor] == [2, 2, 3, 3, 2, 3, 2, 2, 2, 3, 3]
    with_fields = [data for data in raw_frames if data.endswith(b"}}")]
    assert len(with_fields) == 2 and b"SPEED" in with_fields[0]
    assert {m["file"] for m in monitor} == {""}
    assert 'speed "fast" \\ ° ","notes":["x' in monitor[0]["message"]


def test_statistics_count_every_message(tmp_path: Path, hrss_stream: list) -> None:
    """Messages whose heads the sink packs itself are counted per channel on close."""
    path = tmp_path / "n.mcap"
    with McapSink(path, hrss_context(), chunk_size=2000) as sink:
        feed(sink, hrss_stream)
        assert 0 < sink.messages_written
    assert sink.path == path  # what the CLI says after an interrupted recording
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        counted = {
            summary.channels[cid].topic: n
            for cid, n in summary.statistics.channel_message_counts.items()
        }
    read: dict[str, int] = {}
    for topic, *_ in messages(path):
        read[topic] = read.get(topic, 0) + 1
    assert {t: n for t, n in counted.items() if n} == read
    assert sink.messages_written == summary.statistics.message_count == sum(read.values())
    assert read["/hrss/state"] > 0 and read["/mbmon/events"] > 0
