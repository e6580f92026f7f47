"""The layout of mbmon's MCAP logs: topics, schemas, and how records become messages.

This module owns what the log (and the live Foxglove feed) says, not how MCAP
stores it (:mod:`mbmon.io.mcap.writer`): the topics and their JSON schemas
(``mbmon/schemas/*.json``), the metadata record and profile attachments, and
what goes into each message:

- ``/modbus/frames``: a record's ``read --json`` object (frames, noise) without
  its ``line`` and its null members (format 2: :data:`LOG_FORMAT`);
- ``/modbus/monitor``: its monitor line as a ``foxglove.Log`` message (the
  record index in ``line``, the conversation in ``name``, ``file`` empty);
- ``/mbmon/events``: events' objects, noise and CRC errors again, and the
  writer's own stats (index null) every :data:`STATS_EVERY` seconds of capture time;
- ``/hrss/commands``: command records' objects; ``/hrss/state``: flat robot state;
- ``/modbus/raw``: captured chunks (base64) and the source events, for a
  lossless ``replay --redecode``.

Every message is JSON and matches its schema; its log and publish times are the
capture time in ns (:func:`log_time_ns`: clamped to what MCAP can hold, the
true time stays in the message). Two ways to the same bytes:

- :func:`item_messages` / :meth:`LogLayout.messages`: one record or chunk to
  ``(topic, log_time_ns, json_bytes)`` messages, for any consumer (the live
  Foxglove feed serves these over WebSocket);
- :meth:`LogLayout.convert`: the log writer's fused batch form (message
  records with packed MCAP heads, frame records on a fast path), whose bytes
  equal the former's (a differential test keeps them so).
"""

from __future__ import annotations

import base64
import json
import math
import re
import struct
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

from mbmon.format import _JSON_KEYS, View, record_to_json
from mbmon.format import finite as _finite
from mbmon.io.mcap.proto import (
    PROTO_NAMES,
    descriptor_set,
    encode_frame,
    encode_raw,
    varint,
)
from mbmon.io.mcap.writer import MAX_LOG_TIME, MESSAGE_HEAD
from mbmon.jsonfmt import record_json_bytes
from mbmon.model import Chunk, Direction, Event, EventKind, Record, RecordKind, Stream
from mbmon.protocol.mbap import encode_adu

_json_str = json.encoder.encode_basestring  # C-accelerated, keeps non-ASCII
_DIRECTIONS = {d: d.value for d in Direction}
#: a /modbus/raw chunk message: prefix (type, stream, direction, "ts":), ts, base64 data
_decode_json = json.loads  # a format-2 object as made, before it goes to protobuf
_TS_KEY = bytes([8 << 3 | 1])  # modbus.Raw.ts, a double
_DATA_KEY = bytes([9 << 3 | 2])  # modbus.Raw.data, length-delimited
_DOUBLE = struct.Struct("<d")


@cache
def _ts_null() -> bytes:
    """The extra member of a chunk at a non-finite time (made when first needed: encoding
    reads the .proto file, which a log's every run need not)."""
    return encode_raw({"ts": None})


def _pack_ts(ts: float) -> bytes:
    return _TS_KEY + _DOUBLE.pack(ts)


def _data_field(data: bytes) -> bytes:
    n = len(data)
    if n < 0x80:
        return _DATA_KEY + bytes((n,)) + data
    return _DATA_KEY + varint(n) + data


#: the log format this layout writes, stored as the metadata key ``format`` (a log
#: without the key is format 1). Format 2 (docs/logs.md, "Format versions"): a
#: /modbus/frames message is the ``read --json`` object without ``line`` (the record's
#: /modbus/monitor message holds it) and without its members whose value is null; a
#: /modbus/raw chunk message has no ``event``/``info`` (null in format 1); the monitor
#: message's ``file`` is empty (the source is the metadata's). Format 3: the same
#: objects of /modbus/frames and /modbus/raw as protobuf messages (``modbus.Frame``,
#: ``modbus.Raw``: :mod:`mbmon.io.mcap.proto`), which the reader gives back as format
#: 2's objects. Format 4: format 3 without the /modbus/raw message of a chunk that is
#: exactly the ADU of the frame record written right after it (:func:`chunk_marker`);
#: that frame's message ends with ``chunk`` (its direction) instead, and readers
#: rebuild the chunk from the frame (:func:`frame_chunk`). Readers take every format:
#: :func:`full_frame_object` gives a stored frames object its format 1 shape.
LOG_FORMAT = 4
#: a member whose value is null, in an object's JSON: keys are lower-case words, and a
#: string's own quotes are escaped, so ``,"`` opens a member name (or an array's next
#: string, which a colon never follows)
_NULL_MEMBER = re.compile(rb',"[a-z_]+":null(?=[,}])')
#: the nested member of a frame's JSON (the decoder's extra fields), always the last
_FIELDS_MEMBER = b',"fields":'
_HEAD_SIZE = MESSAGE_HEAD.size

#: one message: (topic, log time in ns, JSON bytes)
Message = tuple[str, int, bytes]

TOPIC_RAW = "/modbus/raw"
TOPIC_FRAMES = "/modbus/frames"
TOPIC_MONITOR = "/modbus/monitor"
TOPIC_STATE = "/hrss/state"
TOPIC_COMMANDS = "/hrss/commands"
TOPIC_EVENTS = "/mbmon/events"

#: topics written only when a profile is in force (no empty channels otherwise)
PROFILE_TOPICS = frozenset({TOPIC_STATE, TOPIC_COMMANDS})

#: topic -> schema file stem in ``mbmon/schemas`` (also the MCAP schema name)
TOPIC_SCHEMAS: dict[str, str] = {
    TOPIC_RAW: "modbus.Raw.v2",
    TOPIC_FRAMES: "modbus.Frame.v3",  # formats 3 and 4 (v2: format 2, v1: format 1)
    TOPIC_MONITOR: "foxglove.Log",
    TOPIC_STATE: "hrss.State.v1",
    TOPIC_COMMANDS: "hrss.Command.v1",
    TOPIC_EVENTS: "mbmon.Event.v1",
}

#: topics whose messages are protobuf (log format 3) -> their schema's message name;
#: TOPIC_SCHEMAS keeps their JSON schema: the object a reader gives back
PROTO_TOPICS: dict[str, str] = PROTO_NAMES


def channel_schema(topic: str) -> tuple[str, str, bytes, str]:
    """How a writer (a log, the live Foxglove feed) declares ``topic``'s channel:
    schema name, schema encoding, schema data and message encoding."""
    proto_name = PROTO_TOPICS.get(topic)
    if proto_name is not None:
        return proto_name, "protobuf", descriptor_set(), "protobuf"
    name = TOPIC_SCHEMAS[topic]
    return name, "jsonschema", schema_text(name), "json"


#: topics that carry the ``read --json`` object of a record (merged by index on replay)
RECORD_TOPICS = (TOPIC_FRAMES, TOPIC_EVENTS, TOPIC_COMMANDS)

#: events that come from a source (fed into the pipeline), as opposed to the
#: ones pairing makes up (timeouts); only these are re-fed by ``replay --redecode``
SOURCE_EVENTS = frozenset({EventKind.CONNECT, EventKind.DISCONNECT, EventKind.GAP, EventKind.ERROR})

METADATA_NAME = "mbmon"
PROFILE_MEDIA_TYPE = "application/toml"

# foxglove.LogLevel
LOG_DEBUG, LOG_INFO, LOG_WARNING, LOG_ERROR = 1, 2, 3, 4
#: a /modbus/monitor message (foxglove.Log): sec, nsec, level, the line (a JSON string),
#: its stream's tail (:data:`_MONITOR_TAIL`) and the record index
_MONITOR = b'{"timestamp":{"sec":%d,"nsec":%d},"level":%d,"message":%b%b%d}'
_MONITOR_TAIL = b',"name":%b,"file":%b,"line":'  # name and file as JSON strings
#: the same in two parts, for frame records: the timestamp (sec, nsec), made once per
#: capture time, then the rest with the level filled in (one value less to format)
_MONITOR_STAMP = b'{"timestamp":{"sec":%d,"nsec":%d},"level":'
_MONITOR_INFO, _MONITOR_WARNING = (
    b'%%b%d,"message":%%b%%b%%d}' % level for level in (LOG_INFO, LOG_WARNING)
)
assert _MONITOR_STAMP + b'%d,"message":%b%b%d}' == _MONITOR
_FRAME_KINDS = (RecordKind.REQUEST, RecordKind.RESPONSE, RecordKind.EXCEPTION)
#: format 4: the ``chunk`` member of a frame whose chunk is left out, by direction, and
#: its bytes at the end of the ``modbus.Frame`` message (field 21, a string of three)
CHUNK_DIRECTIONS = {"c2s": Direction.C2S, "s2c": Direction.S2C}
CHUNK_MARKS = {Direction.C2S: b"\xaa\x01\x03c2s", Direction.S2C: b"\xaa\x01\x03s2c"}
#: enum members as module constants: ``RecordKind.RESPONSE`` costs a class attribute
#: lookup through the enum machinery each time, several per record
_RESPONSE, _EXCEPTION = RecordKind.RESPONSE, RecordKind.EXCEPTION


STATS_EVERY = 10.0  # seconds of capture time between the writer's own stats events
#: capture times (s) whose log time fits a message record; outside, log times are clamped
_MAX_TS = MAX_LOG_TIME // 1000 / 1_000_000 - 1.0


def schema_text(name: str) -> bytes:
    """The JSON schema file ``mbmon/schemas/<name>.json`` as bytes."""
    return resources.files("mbmon").joinpath("schemas", f"{name}.json").read_bytes()


try:  # several times faster than the standard encoder; NaN/inf become null
    import orjson as _orjson
except ImportError:  # pragma: no cover - orjson is a dependency
    _orjson = None  # type: ignore[assignment]

#: a float as a JSON number that reads back as the same float (orjson: about 4x faster
#: than repr; both print the shortest round-trip digits)
_float_json: Callable[[float], bytes] = (
    _orjson.dumps if _orjson is not None else lambda x: repr(x).encode()
)

_ENCODER = json.JSONEncoder(ensure_ascii=False, separators=(",", ":"), allow_nan=False, default=str)


def encode(obj: Any) -> bytes:
    """Compact JSON bytes of one message (non-finite numbers become null)."""
    if _orjson is not None:
        try:
            return bytes(_orjson.dumps(obj, default=str))
        except TypeError:  # non-string keys: the standard encoder converts them
            pass
    try:
        text = _ENCODER.encode(obj)
    except ValueError:
        text = _ENCODER.encode(_finite(obj))
    return text.encode("utf-8")


def slim_frame_json(json_line: bytes, start: int, end: int) -> bytes:
    """A frame record's /modbus/frames message (format 2) made from its ``read --json``
    line, whose line string (quotes included) is ``json_line[start:end]``: that member
    cut out, and the members whose value is null left out (those before the nested
    ``fields``, which keeps its own). The compiled core does the same in place."""
    body = json_line[: start - 8] + json_line[end:]  # 8: ',"line":'
    cut = body.find(_FIELDS_MEMBER)
    if cut < 0:
        return _NULL_MEMBER.sub(b"", body)
    cut += 1  # the comma that ends the member before "fields" is the match's look-ahead
    return _NULL_MEMBER.sub(b"", body[:cut]) + body[cut:]


def slim_frame_object(obj: Mapping[str, Any]) -> dict[str, Any]:
    """A /modbus/frames object as format 2 stores it (:func:`slim_frame_json`'s rule)."""
    return {k: v for k, v in obj.items() if v is not None and k != "line"}


def full_frame_object(obj: dict[str, Any]) -> dict[str, Any]:
    """A stored /modbus/frames object in format 1's shape, the ``read --json`` object:
    an object of format 2 (no ``line``) gets every member of the record object back in
    its order, null where format 2 left it out, ``line`` null for the reader to fill in
    from the record's /modbus/monitor message (:func:`mbmon.io.replay.logged_records`),
    and never format 4's ``chunk`` (the log's, not the record's); an object of format 1
    is returned as it is."""
    if "line" in obj:
        return obj
    get = obj.get
    out = {key: get(key) for key in _JSON_KEYS}
    for key, value in obj.items():
        if key not in out and key != "chunk":
            out[key] = value
    return out


def chunk_marker(chunk: Chunk, record: Record, obj: Mapping[str, Any]) -> bytes | None:
    """Format 4's rule, the one definition both writers follow: the bytes that end the
    /modbus/frames message of ``record`` (whose format-2 object is ``obj``) when the
    /modbus/raw message of ``chunk``, written right before it, is left out; ``None``
    when the chunk keeps its message.

    It is left out when the frame's ADU is the whole chunk: a frame record of the
    chunk's stream and direction (not a bus), a timed stream, a plausible capture time
    equal to the record's, integer ``tid`` and ``unit``, and the chunk's bytes exactly
    the MBAP header (tid, protocol id 0, length) and unit before the frame's pdu, so a
    reader rebuilds the chunk from the frame (:func:`frame_chunk`). Anything else (RTU
    over TCP, noise, two ADUs or part of one, another protocol id) fails the byte
    comparison."""
    frame = record.frame
    stream = chunk.stream
    direction = chunk.direction
    ts = chunk.ts
    if (
        frame is None
        or record.kind not in _FRAME_KINDS
        or frame.direction is not direction
        or direction is Direction.BUS
        or not stream.timed
        or not 0.0 < ts < _MAX_TS
        or ts != record.ts
        or obj.get("time") != ts
        or obj.get("stream") != stream.id
    ):
        return None
    tid, unit, pdu_hex = obj.get("tid"), obj.get("unit"), obj.get("pdu")
    if type(tid) is not int or type(unit) is not int or type(pdu_hex) is not str:
        return None
    try:
        adu = encode_adu(tid, unit, bytes.fromhex(pdu_hex))
    except ValueError:  # a tid or unit out of range, a pdu that is no hex
        return None
    return CHUNK_MARKS[direction] if chunk.data == adu else None


def frame_chunk(obj: Mapping[str, Any]) -> dict[str, Any] | None:
    """The /modbus/raw object (format 2's chunk object) a format-4 frames object with
    ``chunk`` stands for (:func:`chunk_marker`), or ``None`` when it has no ``chunk``;
    ``ValueError`` when it has one but not what the chunk is made of (a damaged
    message: its chunk is lost)."""
    direction = obj.get("chunk")
    if direction is None:
        return None
    if type(direction) is not str or direction not in CHUNK_DIRECTIONS:
        shown = repr(direction) if type(direction) is str and len(direction) < 20 else "it"
        raise ValueError(f"{shown} is not a chunk's direction (c2s or s2c)")
    tid, unit, pdu_hex, ts = obj.get("tid"), obj.get("unit"), obj.get("pdu"), obj.get("time")
    if type(tid) is not int or type(unit) is not int or type(pdu_hex) is not str:
        raise ValueError("a frame marked with its chunk has no tid, unit or pdu")
    if type(ts) is not float or obj.get("stream") is None:
        raise ValueError("a frame marked with its chunk has no time or stream")
    src, dst = obj.get("src"), obj.get("dst")
    if type(src) is not str or type(dst) is not str or obj.get("transport") is None:
        raise ValueError("a frame marked with its chunk has no endpoints")
    try:
        adu = encode_adu(tid, unit, bytes.fromhex(pdu_hex))
    except ValueError:
        raise ValueError(
            "a frame marked with its chunk has a pdu, tid or unit it cannot be"
        ) from None
    c2s = direction == "c2s"
    return {
        "type": "chunk",
        "stream": obj["stream"],
        "transport": obj["transport"],
        "client": src if c2s else dst,
        "server": dst if c2s else src,
        "direction": direction,
        "ts": ts,
        "data": base64.b64encode(adu).decode("ascii"),
    }


def proto_payload(topic: str, obj: Any) -> bytes:
    """A /modbus/frames or /modbus/raw object of any format as format 3 stores it (a
    live feed serving a format-1 or format-2 log on its protobuf channels)."""
    if not isinstance(obj, dict):
        raise TypeError(f"a {topic} payload is not an object")
    if topic == TOPIC_FRAMES:
        return encode_frame(slim_frame_object(obj))
    if obj.get("type") == "chunk":  # format 1's null event and info are not in format 2
        obj = {k: v for k, v in obj.items() if k not in ("event", "info") or v is not None}
    return encode_raw(obj)


def stream_name(stream: Stream | None) -> str:
    """The ``name`` of a monitor message: which conversation a line belongs to."""
    if stream is None:
        return "mbmon"
    if stream.client == stream.server:
        return f"#{stream.id} {stream.client}"
    return f"#{stream.id} {stream.client} <> {stream.server}"


def log_level(record: Record, obj: Mapping[str, Any]) -> int:
    """foxglove.LogLevel of a record's monitor line."""
    kind = record.kind
    if kind is RecordKind.REQUEST or kind is RecordKind.RESPONSE:
        if obj.get("malformed") or obj.get("crc_ok") is False:
            return LOG_WARNING
        if record.request is None and kind is RecordKind.RESPONSE:
            return LOG_WARNING  # unsolicited
        return LOG_INFO
    if kind is RecordKind.EXCEPTION:
        return LOG_WARNING
    if kind is RecordKind.NOISE:
        return LOG_ERROR
    if kind is RecordKind.EVENT and record.event is not None:
        ek = record.event.kind
        if ek is EventKind.ERROR:
            return LOG_ERROR
        if ek is EventKind.STATS:
            return LOG_DEBUG
        if ek in (EventKind.GAP, EventKind.TIMEOUT, EventKind.UNSOLICITED):
            return LOG_WARNING
        return LOG_INFO
    if kind is RecordKind.COMMAND and record.command is not None:
        phase = record.command.phase.value
        if phase == "fail":
            return LOG_ERROR
        if phase == "warning":
            return LOG_WARNING
    return LOG_INFO


def profile_bindings(specs: list[str], profiles: list[tuple[str, str]]) -> list[list[Any]]:
    """``[spec, attachment number]`` for each ``--profile`` spec of the recording.

    The profile a spec names (a built-in or a file) is recognised by its text
    among the profiles in force, so ``replay --redecode`` can bind the stored
    copy exactly as recorded even when names and file names differ.
    """
    out: list[list[Any]] = []
    texts = [text for _, text in profiles]
    for spec in specs:
        _target, eq, name = spec.rpartition("=")
        name = name.strip() if eq else spec.strip()
        try:
            from mbmon.semantics.profile import BUILTIN_PROFILES, builtin_profile_text

            if name in BUILTIN_PROFILES:
                text = builtin_profile_text(name)
            else:
                text = Path(name).read_text("utf-8")
        except (OSError, UnicodeDecodeError, ValueError, ImportError):
            continue
        if text in texts:
            out.append([spec, texts.index(text)])
    return out


def log_time_ns(ts: float) -> int:
    """A capture time as a message's log time: ns, to the microsecond, within 0..2**64-1.

    ``round(ts * 1e9)`` would turn 1795317020.786844 into ...786843904 ns: an
    epoch-seconds float has about 0.24 us resolution, so microseconds are all
    it can carry faithfully (and all that pcap records). Times an MCAP record
    cannot hold (negative, NaN, past the year 2554) are clamped: the message
    keeps the true time in its JSON.
    """
    if 0.0 < ts < _MAX_TS:
        return round(ts * 1_000_000) * 1000
    return MAX_LOG_TIME if ts >= _MAX_TS else 0


def plausible_time(ts: float) -> bool:
    """Whether a capture time fits a log time unclamped (and a calendar)."""
    return 0.0 <= ts < _MAX_TS


def topics(profiles: bool) -> list[str]:
    """The topics of a log, in channel order: the /hrss ones only with profiles in force."""
    return [t for t in TOPIC_SCHEMAS if profiles or t not in PROFILE_TOPICS]


def metadata(
    *,
    version: str,
    command_line: Iterable[str],
    source: str,
    profiles: list[tuple[str, str]],
    profile_specs: list[str],
    timeout: float,
    baud: int | None,
    view: View,
    started_ns: int,
) -> dict[str, str]:
    """The ``mbmon`` metadata record: provenance and the analysis settings (docs/logs.md)."""
    return {
        "version": version,
        "format": str(LOG_FORMAT),
        "command_line": json.dumps(list(command_line), ensure_ascii=False),
        "source": source,
        "profiles": json.dumps([name for name, _ in profiles], ensure_ascii=False),
        "profile_bindings": json.dumps(
            profile_bindings(profile_specs, profiles), ensure_ascii=False
        ),
        "profile_specs": json.dumps(list(profile_specs), ensure_ascii=False),
        "timeout": json.dumps(timeout),
        "baud": json.dumps(baud),
        "robot": view.robot or "",
        "robot_is_client": "true" if view.robot_is_client else "false",
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(started_ns / 1e9)),
    }


def profile_attachment_name(name: str) -> str:
    return name if name.endswith(".toml") else f"{name}.toml"


def _stream_fields(stream: Stream | None) -> dict[str, Any]:
    if stream is None:
        return {"stream": None, "transport": None, "client": None, "server": None}
    fields = {
        "stream": stream.id,
        "transport": stream.transport.value,
        "client": stream.client,
        "server": stream.server,
    }
    if not stream.timed:  # a raw RTU dump: its times are placeholders (replay --redecode)
        fields["timed"] = False
    return fields


@dataclass(slots=True)
class Totals:
    """A log's running counters, as of the messages in its chunks.

    :meth:`LogLayout.convert` works on a copy and returns it; the writer keeps
    it with the messages it made (``McapFileWriter.take_from``), so counters
    and chunks never disagree, whatever interrupts a batch.
    """

    kinds: dict[RecordKind, int] = field(default_factory=lambda: dict.fromkeys(RecordKind, 0))
    #: noise bytes, CRC errors, raw chunks and their bytes
    counts: dict[str, int] = field(
        default_factory=lambda: dict.fromkeys(("noise_bytes", "crc_errors", "chunks", "bytes"), 0)
    )
    #: messages per channel whose heads the layout packed one by one
    messages: dict[int, int] = field(default_factory=dict)
    slow_frames: int = 0  # frame records that took the general path (counted in messages)
    next_stats: float = 0.0  # capture time the next stats event is due (0: none yet)
    last_ts: float | None = None  # capture time of the last record
    #: chunks whose /modbus/raw message was left out (format 4: counted in ``chunks``)
    left_out: int = 0

    def copy(self) -> Totals:
        return Totals(
            dict(self.kinds), dict(self.counts), dict(self.messages),
            self.slow_frames, self.next_stats, self.last_ts, self.left_out,
        )  # fmt: skip


class LogLayout:
    """Makes the messages of one log (or one live feed): its view, source and channels.

    ``channels`` maps the topics this log has (:func:`topics`) to channel ids;
    state of a log without ``/hrss/state`` is left out, command records go to
    ``/mbmon/events`` then. Per-stream pieces of messages are cached by stream
    id, so one layout serves one run.
    """

    def __init__(self, view: View, source: str, channels: Mapping[str, int]) -> None:
        self.view = view
        self.channels = dict(channels)
        self._topic_of_channel = {cid: topic for topic, cid in self.channels.items()}
        events = self.channels[TOPIC_EVENTS]
        self._ch_raw = self.channels[TOPIC_RAW]
        self._ch_frames = self.channels[TOPIC_FRAMES]
        self._ch_monitor = self.channels[TOPIC_MONITOR]
        self._ch_events = events
        self._ch_state = self.channels.get(TOPIC_STATE)
        self._ch_commands = self.channels.get(TOPIC_COMMANDS, events)
        self._topic_of = {
            RecordKind.REQUEST: self._ch_frames,
            RecordKind.RESPONSE: self._ch_frames,
            RecordKind.EXCEPTION: self._ch_frames,
            RecordKind.NOISE: self._ch_frames,
            RecordKind.EVENT: events,
            RecordKind.COMMAND: self._ch_commands,
        }
        self._file_json = b'""'  # format 2: the source is the metadata's, not every line's
        self._raw_prefix: dict[tuple[int, Direction], bytes] = {}
        self._tails: dict[int, bytes] = {}
        self._t = Totals()  # the batch in the making (convert's working copy)

    def new_totals(self) -> Totals:
        """Counters of an empty log."""
        return Totals(messages=dict.fromkeys(self.channels.values(), 0))

    # ------------------------------------------------------------------ one at a time

    def waiting_item(self, record: Record) -> tuple[Record, bytes | dict[str, Any]]:
        """What :meth:`convert` takes for a record: the record and its ``read --json``
        line (frames, made from cached parts) or object (other records).

        A record whose time cannot be shown (far beyond any calendar) becomes a
        notice that says so, with its index and the time as a number: it is
        reported, and the log stays readable.
        """
        try:
            if record.frame is not None:
                return record, record_json_bytes(record, self.view)
            return record, record_to_json(record, self.view)
        except (OverflowError, OSError, ValueError) as exc:
            notice = Record(
                record.index, 0.0, RecordKind.EVENT, record.stream,
                event=Event(0.0, record.stream, EventKind.NOTICE, {
                    "message": f"record {record.index} ({record.kind.value}) not logged: its "
                    f"capture time {record.ts!r} cannot be shown ({exc})",
                    "time": record.ts if math.isfinite(record.ts) else None,
                }),
            )  # fmt: skip
            return notice, record_to_json(notice, self.view)

    def messages(self, item: Record | Chunk) -> list[Message]:
        """The messages of one record (on its topics, in log order) or of one captured
        chunk (on ``/modbus/raw``), as ``(topic, log_time_ns, json_bytes)``: the same
        bytes the log holds, without the writer's stats events.

        This is the reusable form of the layout: a live Foxglove feed serves these
        messages (same topics, same schemas) over WebSocket. No I/O, no counters;
        per-stream pieces are cached in the layout.
        """
        totals = self.new_totals()
        totals.next_stats = math.inf  # stats events are the log writer's
        waiting = [item if isinstance(item, Chunk) else self.waiting_item(item)]
        records, _first, _last, _totals = self.convert(waiting, totals)
        return self.split(b"".join(records))

    def split(self, data: bytes) -> list[Message]:
        """Message records (packed heads and data) back into ``(topic, log_time, data)``."""
        out: list[Message] = []
        p, n = 0, len(data)
        topic_of = self._topic_of_channel
        while p < n:
            _op, length, channel, _seq, log_time, _pub = MESSAGE_HEAD.unpack_from(data, p)
            end = p + 9 + length
            out.append((topic_of[channel], log_time, data[p + _HEAD_SIZE : end]))
            p = end
        return out

    # ------------------------------------------------------------------ the writer's batches

    def convert(
        self, items: list[Any], totals: Totals | None
    ) -> tuple[list[bytes], int, int, Totals]:
        """The message records of waiting chunks and records (one or more bytes per item,
        in order), their first and last log time, and the counters ``totals`` (``None``:
        an empty log's) with them counted: a new object, ``totals`` is left as it was.
        Items are chunks and :meth:`waiting_item` tuples. The writer runs it with its
        lock held (in either thread).

        A frame record's /modbus/frames message is its ``read --json`` line and its
        /modbus/monitor message takes the line's JSON-escaped text cut out of that
        line; other records go through :meth:`_obj_messages`. This is the writer's
        per-record work, so it is one loop with the layout's state in locals, and what
        depends on the capture time alone (log time, the monitor's timestamp) is
        made once per distinct time: a chunk and the records it completes share it.

        Format 4: a chunk followed by a frame record's item waits for it, and its
        /modbus/raw message is left out when :func:`chunk_marker` says so (the frame's
        message then ends with the marker); a chunk that is the last item is written
        as it is (the log writer keeps such a chunk waiting for the next batch).
        """
        t = self._t = (totals if totals is not None else self.new_totals()).copy()
        out: list[bytes] = []
        append = out.append
        pack = MESSAGE_HEAD.pack
        first = last = -1
        kinds, tails, raw_prefix = t.kinds, self._tails, self._raw_prefix
        ch_frames, ch_monitor, ch_raw = self._ch_frames, self._ch_monitor, self._ch_raw
        n_chunks = n_bytes = 0
        last_ts: float | None = None
        time_of = log_time = 0  # the capture time whose log time and stamp are below
        next_stats = t.next_stats
        stamp = b""
        held: Chunk | None = None  # a chunk whose message waits for the frame after it
        held_message = b""
        n_items = len(items)
        for i, item in enumerate(items):
            if type(item) is not tuple:  # a Chunk, on /modbus/raw
                ts = item.ts
                if ts != time_of:  # log_time_ns(ts), inline
                    if 0.0 < ts < _MAX_TS:
                        log_time = round(ts * 1_000_000) * 1000
                    else:
                        log_time = log_time_ns(ts)
                    time_of, stamp = ts, b""
                body = self._raw_body(item, raw_prefix)
                n_chunks += 1
                n_bytes += len(item.data)
                message = pack(5, 22 + len(body), ch_raw, 0, log_time, log_time) + body
                if i + 1 < n_items and type(items[i + 1]) is tuple:
                    held, held_message = item, message  # the record decides (format 4)
                else:
                    append(message)
            else:
                record, payload = item
                ts = last_ts = record.ts
                if ts != time_of:
                    time_of, log_time, stamp = ts, log_time_ns(ts), b""
                frame = record.frame
                start = end = 0
                if type(payload) is bytes:
                    if payload[-2] != 125:  # no "fields" object at the end (no "}}")
                        end = payload.rfind(b'","notes":[') + 1  # just past the line's end
                        start = payload.rfind(b',"line":"', 0, end) + 8  # its opening quote
                    else:  # a "fields" key could hold anything: search from the start
                        start = payload.find(b',"line":"') + 8
                        end = payload.find(b'","notes":', start) + 1
                if start < 8 or end <= start or frame is None:  # not a frame line: slow path
                    if type(payload) is bytes:
                        payload = record_to_json(record, self.view)
                    self._add_chunk_counts(n_chunks, n_bytes)  # its stats may be due
                    n_chunks = n_bytes = 0
                    mark = self._held_mark(held, held_message, record, payload, append)
                    held = None
                    append(self._obj_messages(record, payload, log_time, mark))
                    next_stats = t.next_stats
                else:
                    kind = record.kind
                    kinds[kind] += 1  # also the count of its two messages (told on close)
                    if not stamp:
                        stamp = _MONITOR_STAMP % divmod(log_time, 1_000_000_000)
                    crc_error = frame.crc_ok is False and kind is _RESPONSE
                    monitor = (
                        _MONITOR_WARNING
                        if kind is _EXCEPTION
                        or frame.crc_ok is False
                        or frame.pdu.malformed
                        or (kind is _RESPONSE and record.request is None)  # unsolicited
                        else _MONITOR_INFO
                    )
                    tail = tails.get(frame.stream.id)
                    if tail is None:
                        tail = self.monitor_tail(frame.stream)
                    monitor %= (stamp, payload[start:end], tail, record.index)
                    obj = _decode_json(slim_frame_json(payload, start, end))
                    slim = encode_frame(obj) + self._held_mark(
                        held, held_message, record, obj, append
                    )
                    held = None
                    n = len(slim)
                    out += (
                        pack(5, 22 + n, ch_frames, 0, log_time, log_time),
                        slim,
                        pack(5, 22 + len(monitor), ch_monitor, 0, log_time, log_time),
                        monitor,
                    )
                    if crc_error:
                        t.counts["crc_errors"] += 1
                        append(self._head(self._ch_events, log_time, len(payload)) + payload)
                    if record.state is not None:
                        append(self._state_message(record, log_time))
                    if ts >= next_stats:
                        self._add_chunk_counts(n_chunks, n_bytes)
                        n_chunks = n_bytes = 0
                        append(self._due_stats(ts, log_time))
                        next_stats = t.next_stats
            if first < 0 or log_time < first:  # log times are never negative
                first = log_time
            if log_time > last:
                last = log_time
        self._add_chunk_counts(n_chunks, n_bytes)
        if last_ts is not None:
            t.last_ts = last_ts
        return out, first, last, t

    def _raw_body(self, chunk: Chunk, prefixes: dict[tuple[int, Direction], bytes]) -> bytes:
        """A chunk's /modbus/raw message (its data, without the record head)."""
        stream = chunk.stream
        prefix = prefixes.get((stream.id, chunk.direction))
        if prefix is None:
            prefix = self.raw_prefix(stream, chunk.direction)
        ts = chunk.ts
        if ts - ts == 0.0:  # finite
            return prefix + _pack_ts(ts) + _data_field(chunk.data)
        # format 2's null (JSON has no NaN, no infinity): in extra
        return prefix + _data_field(chunk.data) + _ts_null()

    def _held_mark(
        self,
        held: Chunk | None,
        message: bytes,
        record: Record,
        obj: Mapping[str, Any],
        append: Callable[[bytes], None],
    ) -> bytes:
        """Format 4, for the record right after a held chunk (``None``: no chunk held):
        the marker that ends its frame's message when the chunk's message is left out
        (:func:`chunk_marker`, counted in :attr:`Totals.left_out`), else ``b""`` with the
        chunk's ``message`` appended first. ``obj``: the record's ``read --json`` object
        (or format 2's slim one: the members the rule reads are the same)."""
        if held is None:
            return b""
        mark = chunk_marker(held, record, obj)
        if mark is None:
            append(message)
            return b""
        self._t.left_out += 1
        return mark

    def _add_chunk_counts(self, chunks: int, size: int) -> None:
        counts = self._t.counts
        counts["chunks"] += chunks  # also the count of their messages (told on close)
        counts["bytes"] += size

    def raw_prefix(self, stream: Stream, direction: Direction) -> bytes:
        """A stream direction's chunk messages up to their ``ts`` field (``modbus.Raw``:
        type, stream, its endpoints, direction), cached here by stream direction; the
        compiled core keeps its own copy. A message is the prefix, the ``ts`` field (a
        double) and the ``data`` field: the fields in the order of the format-2 object's
        members, as :func:`encode_raw` writes them."""
        obj = {"type": "chunk", **_stream_fields(stream), "direction": _DIRECTIONS[direction]}
        prefix = encode_raw(_decode_json(encode(obj)))
        self._raw_prefix[(stream.id, direction)] = prefix
        return prefix

    def _obj_messages(
        self, record: Record, obj: Mapping[str, Any], log_time: int, mark: bytes = b""
    ) -> bytes:
        """The message records of a record made from its ``read --json`` object (noise,
        events, commands: few records, so the plain encoder does); ``mark`` ends a frame's
        /modbus/frames message (format 4: :func:`chunk_marker`)."""
        ts = record.ts
        kind = record.kind
        t = self._t
        t.kinds[kind] += 1
        if kind in _FRAME_KINDS:
            t.slow_frames += 1  # its messages are counted by _head
        payload = encode(obj)
        head = self._head
        n = len(payload)
        topic = self._topic_of[kind]
        if topic == self._ch_frames:  # format 2's object (no line, no nulls) in protobuf
            slim = encode_frame(_decode_json(encode(slim_frame_object(obj)))) + mark
            parts = [head(topic, log_time, len(slim)), slim]
        else:
            parts = [head(topic, log_time, n), payload]
        if kind is RecordKind.NOISE:
            parts += (head(self._ch_events, log_time, n), payload)
            if record.noise is not None:
                t.counts["noise_bytes"] += len(record.noise.raw)
                if "crc" in record.noise.reason.lower():
                    t.counts["crc_errors"] += 1
        elif kind is RecordKind.EVENT:
            event = record.event
            if event is not None and event.kind in SOURCE_EVENTS:
                raw = self._raw_event(event)
                parts += (head(self._ch_raw, log_time, len(raw)), raw)
        elif kind is RecordKind.RESPONSE and obj["crc_ok"] is False:
            t.counts["crc_errors"] += 1
            parts += (head(self._ch_events, log_time, n), payload)
        stream = record.stream
        tail = self._tails.get(stream.id if stream is not None else -1)
        if tail is None:
            tail = self.monitor_tail(stream)
        sec, nsec = divmod(log_time, 1_000_000_000)
        monitor = _MONITOR % (
            sec, nsec, log_level(record, obj), _json_str(obj["line"]).encode(), tail, record.index
        )  # fmt: skip
        parts += (head(self._ch_monitor, log_time, len(monitor)), monitor)
        if record.state is not None:
            parts.append(self._state_message(record, log_time))
        if ts >= t.next_stats:
            parts.append(self._due_stats(ts, log_time))
        return b"".join(parts)

    def monitor_tail(self, stream: Stream | None) -> bytes:
        """The end of a stream's monitor messages (name, file, "line" key), cached by stream id
        (a Stream hashes slowly); -1 stands for records of no stream."""
        tail = _MONITOR_TAIL % (_json_str(stream_name(stream)).encode(), self._file_json)
        self._tails[stream.id if stream is not None else -1] = tail
        return tail

    def _head(self, channel_id: int, log_time: int, size: int) -> bytes:
        """The head of a message record of ``size`` data bytes on a channel (and count it)."""
        self._t.messages[channel_id] += 1
        return MESSAGE_HEAD.pack(5, 22 + size, channel_id, 0, log_time, log_time)

    def _state_message(self, record: Record, log_time: int) -> bytes:
        """The /hrss/state message record of a record that carries robot state."""
        state: dict[str, Any] = {"time": record.ts, "index": record.index}
        for key, value in (record.state or {}).items():
            if isinstance(value, bool):
                state[key] = int(value)
            elif isinstance(value, int | float) and math.isfinite(value):
                state[key] = value  # flat numbers only: NaN/inf have no JSON form
        if self._ch_state is None:  # a log without profiles has no /hrss/state
            return b""
        data = encode(state)
        return self._head(self._ch_state, log_time, len(data)) + data

    def _due_stats(self, ts: float, log_time: int) -> bytes:
        """The stats message record due at ``ts`` (none for the first record)."""
        t = self._t
        data = b""
        if not plausible_time(ts):  # an impossible time schedules nothing
            return data
        if t.next_stats > 0:
            stats = self._stats(t, ts)
            data = self._head(self._ch_events, log_time, len(stats)) + stats
        t.next_stats = ts + STATS_EVERY
        return data

    def final_stats(self, totals: Totals) -> Message | None:
        """The closing stats event (``"final": true``) of a log that holds records."""
        if totals.last_ts is None:
            return None
        ts = totals.last_ts
        return TOPIC_EVENTS, log_time_ns(ts), self._stats(totals, ts, True)

    def channel_counts(self, totals: Totals) -> dict[int, int]:
        """Messages per channel that :meth:`convert` made, as counted by ``totals``:
        those it counted one by one, raw chunks (but those left out), and two per frame
        on the fast path."""
        counts = dict(totals.messages)
        raw = totals.counts["chunks"] - totals.left_out  # format 4: a chunk left out has none
        counts[self._ch_raw] = counts.get(self._ch_raw, 0) + raw
        kinds = totals.kinds
        fast = sum(kinds[k] for k in _FRAME_KINDS) - totals.slow_frames
        counts[self._ch_frames] = counts.get(self._ch_frames, 0) + fast
        counts[self._ch_monitor] = counts.get(self._ch_monitor, 0) + fast
        return counts

    def _raw_event(self, event: Event) -> bytes:
        """A source event's /modbus/raw message (every field, as in format 1)."""
        body = {
            "type": "event",
            **_stream_fields(event.stream),
            "ts": event.ts,
            "direction": None,
            "data": "",
            "event": event.kind.value,
            "info": dict(event.info),
        }
        return encode_raw(_decode_json(encode(body)))

    def _stats(self, totals: Totals, ts: float, final: bool = False) -> bytes:
        """The writer's own counters as an /mbmon/events message (index null)."""
        kinds = totals.kinds
        info: dict[str, Any] = {
            "records": sum(kinds.values()),
            "requests": kinds[RecordKind.REQUEST],
            "responses": kinds[RecordKind.RESPONSE],
            "exceptions": kinds[RecordKind.EXCEPTION],
            "noise": kinds[RecordKind.NOISE],
            "events": kinds[RecordKind.EVENT],
            "commands": kinds[RecordKind.COMMAND],
            **totals.counts,
        }
        if final:
            info["final"] = True
        try:
            line_ts = time.strftime("%H:%M:%S", time.localtime(ts))
        except (OverflowError, OSError, ValueError):  # an impossible capture time
            line_ts = "--:--:--"
        obj: dict[str, Any] = {
            "index": None, "time": ts, "stream": None, "src": None, "dst": None,
            "transport": None, "tid": None, "unit": None, "fc": None, "kind": "event",
            "exception_code": None, "address": None, "count": None, "values": None,
            "pdu": None, "line": "", "notes": None, "crc_ok": None, "latency_ms": None,
            "malformed": None, "request_index": None, "event": "stats", "info": info,
        }  # fmt: skip
        obj["line"] = f"{line_ts}  -- Stats: " + ", ".join(f"{k}={v}" for k, v in info.items())
        return encode(obj)


def item_messages(item: Record | Chunk, view: View, source: str = "") -> list[Message]:
    """The messages of one record or captured chunk as ``(topic, log_time_ns, json_bytes)``,
    exactly as a log made with ``view`` from ``source`` stores them (stats events aside).

    Pure: a throwaway :class:`LogLayout` with every topic. A long-lived consumer
    (the live Foxglove feed) keeps one ``LogLayout(view, source, channels)`` and
    calls :meth:`LogLayout.messages` instead, which caches per-stream pieces.
    """
    return LogLayout(view, source, ALL_CHANNELS).messages(item)


#: every topic on a channel id of its own (channel ids only matter inside one file)
ALL_CHANNELS: dict[str, int] = {topic: n for n, topic in enumerate(TOPIC_SCHEMAS, 1)}
