"""The MCAP layout: the reusable record -> (topic, log_time_ns, json_bytes) form is what
the log holds, byte for byte; impossible capture times leave readable logs."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import sink_records as records
from format4 import as_format3, left_out
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from mbmon.format import View
from mbmon.io.mcap.layout import (
    ALL_CHANNELS,
    TOPIC_SCHEMAS,
    LogLayout,
    full_frame_object,
    item_messages,
    log_time_ns,
    slim_frame_json,
    slim_frame_object,
)
from mbmon.io.mcap.proto import decode_frame, decode_raw
from mbmon.io.mcap.reader import McapLog
from mbmon.io.mcap.writer import MAX_LOG_TIME
from mbmon.model import Chunk, Record
from mbmon.sinks.base import SinkContext
from mbmon.sinks.mcap import McapSink


def logged(path: Path) -> list[tuple[str, int, bytes]]:
    """Every message in file order, as the mcap package reads it, without stats events."""
    out = []
    with open(path, "rb") as f:
        for _, channel, msg in make_reader(f, validate_crcs=True).iter_messages(
            log_time_order=False
        ):
            data = bytes(msg.data)
            if channel.topic == "/mbmon/events" and json.loads(data).get("event") == "stats":
                continue
            assert msg.publish_time == msg.log_time
            out.append((channel.topic, msg.log_time, data))
    return out


@pytest.mark.parametrize("which", ["session", "hrss"])
@pytest.mark.parametrize("robot", [None, "192.168.0.10"])
def test_item_messages_are_the_log(
    tmp_path: Path, which: str, robot: str | None, session_stream: list, hrss_stream: list
) -> None:
    """The function a live feed reuses gives the log's messages, byte for byte."""
    stream = session_stream if which == "session" else hrss_stream
    ctx = records.hrss_context(robot) if which == "hrss" else SinkContext(
        view=View(robot=robot), source="x.pcap"
    )  # fmt: skip
    path = tmp_path / "x.mcap"
    with McapSink(path, ctx, chunk_size=2000) as sink:
        records.feed(sink, stream)
    expected = [m for item in stream for m in item_messages(item, ctx.view, ctx.source)]
    # the log is format 4 (a one-ADU chunk's raw message left out, its frame marked);
    # the live form serves every chunk: the same once the left-out chunks are rebuilt
    assert as_format3(logged(path)) == expected
    assert left_out(logged(path)) > 0
    topics = {t for t, _, _ in expected}
    assert {"/modbus/raw", "/modbus/frames", "/modbus/monitor"} <= topics
    if which == "hrss":
        assert {"/hrss/state", "/hrss/commands"} <= topics
    # one long-lived layout (what a live feed keeps) gives the same
    layout = LogLayout(ctx.view, ctx.source, ALL_CHANNELS)
    assert [m for item in stream for m in layout.messages(item)] == expected


def test_item_messages_signature(session_stream: list) -> None:
    rec = next(x for x in session_stream if isinstance(x, Record) and x.frame is not None)
    msgs = item_messages(rec, View())
    assert [t for t, _, _ in msgs] == ["/modbus/frames", "/modbus/monitor"]
    assert all(lt == log_time_ns(rec.ts) for _, lt, _ in msgs)
    assert decode_frame(msgs[0][2])["index"] == rec.index  # format 3: protobuf
    chunk = next(x for x in session_stream if isinstance(x, Chunk))
    [(topic, lt, data)] = item_messages(chunk, View())
    assert lt == log_time_ns(chunk.ts)
    assert topic == "/modbus/raw" and decode_raw(data)["type"] == "chunk"
    assert set(ALL_CHANNELS) == set(TOPIC_SCHEMAS)


def test_log_time_is_clamped() -> None:
    assert log_time_ns(1_700_000_000.25) == 1_700_000_000_250_000_000
    for ts in (-5.0, 0.0, float("nan"), -float("inf")):
        assert log_time_ns(ts) == 0
    for ts in (1e17, 1.8e19, float("inf")):
        assert log_time_ns(ts) == MAX_LOG_TIME


IMPOSSIBLE = [1e17, 5.5e17, 1.8e19, -5.0, -1e17, float("inf"), float("nan")]


def test_impossible_times_leave_a_readable_log(tmp_path: Path, session_stream: list) -> None:
    """Each record at an impossible time is logged (clamped log time, the true
    time in its JSON) or reported by a notice naming it; the records around it are
    logged and the file is finished."""
    recs = [x for x in session_stream if isinstance(x, Record)]
    chunks = [x for x in session_stream if isinstance(x, Chunk)]
    odd = [dataclasses.replace(recs[1 + i % (len(recs) - 1)], index=1000 + i, ts=ts)
           for i, ts in enumerate(IMPOSSIBLE)]  # fmt: skip
    odd_chunks = [dataclasses.replace(chunks[0], ts=ts) for ts in IMPOSSIBLE]
    stream: list[Chunk | Record] = [*session_stream, *odd_chunks, *odd, *session_stream[:5]]
    path = tmp_path / "odd.mcap"
    with McapSink(path, SinkContext(source="odd")) as sink:
        records.feed(sink, stream)
    with open(path, "rb") as f:
        summary = make_reader(f, validate_crcs=True).get_summary()
    assert summary is not None and summary.statistics is not None
    with McapLog(path) as log:
        assert log.finished
        msgs = list(log.messages())
    assert all(0 <= m.log_time <= MAX_LOG_TIME for m in msgs)
    assert sum(summary.statistics.channel_message_counts.values()) == len(msgs)
    objs = [m.json() for m in msgs if m.topic in ("/modbus/frames", "/mbmon/events")]
    for i, ts in enumerate(IMPOSSIBLE):
        mine = [o for o in objs if o.get("index") == 1000 + i]
        assert mine, f"record at {ts!r} neither logged nor reported"
        obj = mine[0]
        if obj["kind"] == "event" and obj["event"] == "notice":
            assert f"record {1000 + i}" in obj["info"]["message"]
        elif math.isfinite(ts):
            assert obj["time"] == ts
    raw_ts = [m.json()["ts"] for m in msgs if m.topic == "/modbus/raw"]
    rest = iter(raw_ts)  # the chunks at impossible times are logged, in order
    assert all(x in rest for x in [ts if math.isfinite(ts) else None for ts in IMPOSSIBLE])
    # the records after them are all there
    indexes = [m.json()["line"] for m in msgs if m.topic == "/modbus/monitor"]
    tail = [r.index for r in stream[-5:] if isinstance(r, Record)]
    assert tail and indexes[-len(tail) :] == tail


# ---------------------------------------------------------------- format 2's frame messages

_KEYS = (
    "index", "time", "stream", "src", "dst", "transport", "tid", "unit", "fc", "kind",
    "exception_code", "address", "count", "values", "pdu", "line", "notes", "crc_ok",
    "latency_ms", "malformed", "request_index",
)  # fmt: skip


def _line_json(obj: dict) -> tuple[bytes, int, int]:
    """A --json line and where its line string (quotes included) is."""
    data = json.dumps(obj, ensure_ascii=False, separators=(",", ":")).encode()
    start = data.index(b',"line":"') + 8
    return data, start, start + len(json.dumps(obj["line"], ensure_ascii=False).encode())


def test_slim_frame_json_byte_table() -> None:
    """The line member and the null members go; strings that look like members stay."""
    obj = dict.fromkeys(_KEYS)
    obj.update(index=3, time=1.5, stream=0, kind="request", fc=3, pdu="03 00 C8 00 01",
               line='12:00  x ,"crc_ok":null, \\ "', notes=['a":null,"b', ',"fields":{'],
               malformed=None)  # fmt: skip
    obj["fields"] = {"x": None, "y": 1}
    data, start, end = _line_json(obj)
    slim = slim_frame_json(data, start, end)
    if _core_slim is not None:
        assert _core_slim(data, start, end) == slim
    assert slim == (
        b'{"index":3,"time":1.5,"stream":0,"fc":3,"kind":"request","pdu":"03 00 C8 00 01",'
        b'"notes":["a\\":null,\\"b",",\\"fields\\":{"],"fields":{"x":null,"y":1}}'
    )
    assert slim == json.dumps(slim_frame_object(obj), ensure_ascii=False,
                              separators=(",", ":")).encode()  # fmt: skip
    full = full_frame_object(json.loads(slim))
    assert list(full) == [*_KEYS, "fields"] and full["line"] is None
    assert {**full, "line": obj["line"]} == obj


_scalar = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**40), 2**40),
    st.text(alphabet=st.sampled_from('ab:,"\\{}[]n ul°'), max_size=12),
)  # fmt: skip


@settings(max_examples=300, deadline=None)
@given(
    st.fixed_dictionaries({k: _scalar for k in _KEYS if k not in ("index", "line", "kind")}),
    st.text(alphabet=st.sampled_from('ab:,"\\{}n ul'), max_size=20),
    st.lists(st.text(alphabet=st.sampled_from('ab:,"\\{}n ul'), max_size=10), max_size=3),
    st.one_of(st.none(), st.dictionaries(st.sampled_from(["a_b", "c"]), _scalar, max_size=2)),
)
def test_slim_frame_json_is_the_object_rule(
    members: dict, line: str, notes: list, fields: dict | None
) -> None:
    """The writers' byte rule equals the object rule on any members, and a reader gets the
    --json object back (the line from the monitor message)."""
    obj = {k: members.get(k) for k in _KEYS}
    obj.update(index=1, kind="response", line=line, notes=notes)
    if fields:
        obj["fields"] = fields
    data, start, end = _line_json(obj)
    slim = slim_frame_json(data, start, end)
    assert slim == json.dumps(slim_frame_object(obj), ensure_ascii=False,
                              separators=(",", ":")).encode()  # fmt: skip
    assert {**full_frame_object(json.loads(slim)), "line": line} == obj
    if _core_slim is not None:  # the compiled core's in-place rule: the same bytes
        assert _core_slim(data, start, end) == slim


try:
    from mbmon.core._reader import _slim_frame_json as _core_slim
except ImportError:  # no compiled core (MBMON_NO_EXTENSIONS or no compiler): pure only
    _core_slim = None


@pytest.mark.skipif(_core_slim is None, reason="no compiled core")
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=80), st.data())
def test_core_slim_frame_stays_in_bounds_on_any_bytes(data: bytes, draw: st.DataObject) -> None:
    """The core's in-place rule on bytes that are not a JSON line (run under ASan in CI):
    it only ever shortens them, and leaves bytes without a colon as they are but the cut."""
    if len(data) < 9:
        return
    start = draw.draw(st.integers(8, len(data) - 1))
    end = draw.draw(st.integers(start + 1, len(data)))
    assert _core_slim is not None
    out = _core_slim(data, start, end)
    assert len(out) <= len(data) - (end - start + 8)
    if b":" not in data:
        assert out == data[: start - 8] + data[end:]
