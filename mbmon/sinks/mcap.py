"""MCAP log writer (``-w FILE.mcap``): the recording Foxglove opens and ``mbmon replay`` reads.

This module owns the layout of mbmon's MCAP logs: the topics, their JSON
schemas (``mbmon/schemas/*.json``), what goes into each message, the metadata
record and the profile attachments, and the crash-safety policy:

- every message is JSON encoded and matches its schema; log and publish times
  are the capture timestamps in nanoseconds, never the wall clock;
- chunks are zstd compressed (lz4, then none, when those are missing); the
  open chunk is closed every half second of wall time (by ``write()`` while
  records flow, by the writer thread when they stop) and a writer thread
  compresses it and hands it to the OS, so a killed process loses at most the
  last second; zstd, joining the chunk and file writes release the GIL, so
  that work overlaps with decoding;
- ``write()`` and ``write_chunk()`` only queue what they are given (a frame
  record with its ``read --json`` line, made in the calling thread); queued
  items become messages in batches (:meth:`McapSink._make_messages`, the
  per-record work, at most ``_BATCH`` items or at the half-second flush);
- ``close()`` always finishes the file (summary, index, footer); the CLI turns
  SIGINT/SIGTERM into exceptions so ``close()`` runs from ``__exit__``;
- a batch's messages enter the open chunk with one list operation, chunks are
  written by a thread signal handlers never interrupt, and the file is
  finished with SIGINT/SIGTERM held back, so a signal handler that raises can
  never leave half a message or half a chunk in the file (at worst a record
  has some of its topics);
- a write error (disk full) in the writer thread is raised as ``SinkError``
  by a later ``write()`` (the next batch) or by ``close()``.
"""

from __future__ import annotations

import json
import math
import queue
import signal
import struct
import threading
import time
import zlib
from binascii import b2a_base64
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import IO, Any

from mbmon import __version__
from mbmon.format import View, record_json_bytes, record_to_json
from mbmon.model import Chunk, Direction, Event, EventKind, Record, RecordKind, Stream
from mbmon.sinks.base import SinkBase, SinkContext, SinkError

_json_str = json.encoder.encode_basestring  # C-accelerated, keeps non-ASCII
_DIRECTIONS = {d: d.value for d in Direction}
#: a /modbus/raw chunk message: prefix (type, stream, direction, "ts":), ts, base64 data
_RAW_BODY = b'%b%b,"data":"%b","event":null,"info":null}'
MCAP_MAGIC = b"\x89MCAP0\r\n"
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel, sequence, log, publish
_CHUNK_HEAD = struct.Struct("<BQQQQII")  # opcode, length, start, end, size, crc, name length
_U64 = struct.Struct("<Q")
#: makes waiting items into message records: (records, first log time, last log time)
Converter = Callable[[list[Any]], tuple[list[bytes], int, int]]


@dataclass(frozen=True, slots=True)
class PendingChunk:
    """A closed chunk's uncompressed records (in pieces, joined when written) and time range,
    waiting to be written."""

    data: list[bytes]
    start: int
    end: int


TOPIC_RAW = "/modbus/raw"
TOPIC_FRAMES = "/modbus/frames"
TOPIC_MONITOR = "/modbus/monitor"
TOPIC_STATE = "/hrss/state"
TOPIC_COMMANDS = "/hrss/commands"
TOPIC_EVENTS = "/mbmon/events"

#: topic -> schema file stem in ``mbmon/schemas`` (also the MCAP schema name)
TOPIC_SCHEMAS: dict[str, str] = {
    TOPIC_RAW: "modbus.Raw.v1",
    TOPIC_FRAMES: "modbus.Frame.v1",
    TOPIC_MONITOR: "foxglove.Log",
    TOPIC_STATE: "hrss.State.v1",
    TOPIC_COMMANDS: "hrss.Command.v1",
    TOPIC_EVENTS: "mbmon.Event.v1",
}

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
#: enum members as module constants: ``RecordKind.RESPONSE`` costs a class attribute
#: lookup through the enum machinery each time, several per record
_RESPONSE, _EXCEPTION = RecordKind.RESPONSE, RecordKind.EXCEPTION

STATS_EVERY = 10.0  # seconds of capture time between the writer's own stats events
FLUSH_EVERY = 0.5  # seconds of wall time between chunk flushes (at most 1 s is promised)
_BATCH = 128  # records (and raw chunks) moved into the open chunk at once, at most
_SIGNALS = {signal.SIGINT, signal.SIGTERM}
ZSTD_LEVEL = 3  # chunk compression level (1 measured no faster on 1M ADUs, 14 % larger)


def schema_text(name: str) -> bytes:
    """The JSON schema file ``mbmon/schemas/<name>.json`` as bytes."""
    return resources.files("mbmon").joinpath("schemas", f"{name}.json").read_bytes()


def _finite(value: Any) -> Any:
    """Replace NaN/inf (not JSON) by None, recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


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


def _ns(ts: float) -> int:
    """Nanoseconds of a capture time, to the microsecond.

    ``round(ts * 1e9)`` would turn 1795317020.786844 into ...786843904 ns: an
    epoch-seconds float has about 0.24 us resolution, so microseconds are all
    it can carry faithfully (and all that pcap records).
    """
    if ts > 0.0:
        return round(ts * 1_000_000) * 1000
    return 0


def _stream_fields(stream: Stream | None) -> dict[str, Any]:
    if stream is None:
        return {"stream": None, "transport": None, "client": None, "server": None}
    return {
        "stream": stream.id,
        "transport": stream.transport.value,
        "client": stream.client,
        "server": stream.server,
    }


def _pick_compression() -> tuple[str, Callable[[bytes], bytes] | None]:
    """The best chunk compression available: zstd, then lz4, then none."""
    try:
        import zstandard

        return "zstd", zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress
    except ImportError:
        pass
    try:
        import lz4.frame  # type: ignore[import-not-found]

        return "lz4", lz4.frame.compress
    except ImportError:
        return "", None


class McapFileWriter:
    """An MCAP writer for many small messages, built on the ``mcap`` package's records.

    ``mcap.writer.Writer`` spends about 20 us of Python per message (a record
    object, a message index entry, eight small writes); here a message record is
    one ``struct.pack`` of its head and its data, handed over in batches
    (:meth:`take_from`) into the open chunk, a list of pieces joined once when
    the chunk is written, and the ``mcap`` package writes every other record
    (header, schemas, channels, chunks, metadata, attachments, statistics,
    indexes, footer), laid out as
    ``Writer.finish`` does. Schemas and channels are written once, before the
    first chunk and outside it, so that every chunk of a file cut short can be
    read on its own. No message index records are written (readers scan a
    chunk without them); chunk, metadata and attachment indexes are.
    """

    def __init__(self, stream: IO[bytes], *, chunk_size: int = 1 << 20) -> None:
        from mcap.data_stream import RecordBuilder

        self._f = stream
        self._rb = RecordBuilder()
        self.compression, self._compress = _pick_compression()
        self.chunk_size = chunk_size
        #: the open chunk: its message records in pieces, joined once when it is written
        #: (growing one buffer would copy every byte again at each reallocation)
        self._parts: list[bytes] = []
        self._size = 0  # bytes in _parts
        self._chunk_start = 0
        self._chunk_end = 0
        self._schemas: list[Any] = []
        self._channels: list[Any] = []
        self._counts: dict[int, int] = {}
        self._start_time = 0
        self._end_time = 0
        self._chunk_indexes: list[Any] = []
        self._metadata_indexes: list[Any] = []
        self._attachment_indexes: list[Any] = []

    def _emit(self) -> None:
        self._f.write(self._rb.end())

    def start(self, library: str) -> None:
        from mcap.records import Header

        self._f.write(MCAP_MAGIC)
        Header(profile="", library=library).write(self._rb)
        self._emit()

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        from mcap.records import Schema

        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        schema.write(self._rb)
        self._emit()
        return int(schema.id)

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        from mcap.records import Channel

        channel = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata={},
        )
        self._channels.append(channel)
        self._counts[channel.id] = 0
        channel.write(self._rb)
        self._emit()
        return int(channel.id)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        from mcap.records import Metadata, MetadataIndex

        offset = self._f.tell()
        Metadata(name=name, metadata=data).write(self._rb)
        length = self._rb.count
        self._emit()
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add_attachment(
        self, create_time: int, log_time: int, name: str, media_type: str, data: bytes
    ) -> None:
        from mcap.records import Attachment, AttachmentIndex

        offset = self._f.tell()
        Attachment(
            create_time=create_time, log_time=log_time, name=name, media_type=media_type, data=data
        ).write(self._rb)
        length = self._rb.count
        self._emit()
        self._attachment_indexes.append(
            AttachmentIndex(
                offset=offset,
                length=length,
                create_time=create_time,
                log_time=log_time,
                data_size=len(data),
                name=name,
                media_type=media_type,
            )
        )

    def _span(self, start: int, end: int) -> None:
        """Widen the open chunk's time range to take messages logged from ``start`` to ``end``."""
        if not self._parts:
            self._chunk_start, self._chunk_end = start, end
        else:
            if start < self._chunk_start:
                self._chunk_start = start
            if end > self._chunk_end:
                self._chunk_end = end

    def append(self, channel_id: int, log_time: int, data: bytes) -> int:
        """Append one message to the open chunk; return the chunk's size (the caller closes it).

        The message goes in with one list append, so a signal handler that
        raises between bytecodes can never leave half a message in the chunk.
        """
        self._span(log_time, log_time)
        record = _MESSAGE_HEAD.pack(0x05, 22 + len(data), channel_id, 0, log_time, log_time) + data
        self._parts.append(record)
        self._counts[channel_id] += 1
        self._size += len(record)
        return self._size

    def count(self, channel_id: int, messages: int) -> None:
        """Count ``messages`` more on a channel in the statistics: messages whose heads
        the caller packed itself (with ``_MESSAGE_HEAD``) and handed to :meth:`take_from`."""
        self._counts[channel_id] += messages

    def take_from(self, pending: list[Any], convert: Converter) -> int:
        """Move what waits in ``pending`` to the end of the open chunk as message records
        (``convert`` makes them) and remove it from the list; return the open chunk's
        size (the caller closes it).

        Another thread may append to ``pending`` meanwhile: only the items there at
        the start are moved. The chunk gains their records by one in-place list
        concatenation and the list loses them by one slice deletion, with no call
        in between (where CPython runs signal handlers), so a handler that raises
        leaves every item either in the chunk or still waiting, never both or
        neither.
        """
        n = len(pending)
        if not n:
            return self._size
        records, start, end = convert(pending[:n])
        if records:
            self._span(start, end)
        parts = self._parts
        parts += records
        del pending[:n]
        self._size += sum(map(len, records))
        return self._size

    def add_message(self, channel_id: int, log_time: int, data: bytes) -> None:
        """Append one message; close the chunk when it exceeds ``chunk_size``."""
        if self.append(channel_id, log_time, data) > self.chunk_size:
            self.close_chunk()

    def take_chunk(self) -> PendingChunk | None:
        """Detach the open chunk (``None`` if empty); :meth:`write_chunk` writes it later."""
        parts = self._parts
        if not parts:
            return None
        self._parts = []
        self._size = 0
        return PendingChunk(parts, self._chunk_start, self._chunk_end)

    def write_chunk(self, pending: PendingChunk) -> None:
        """Compress and write a detached chunk, and index it (chunks in order)."""
        from mcap.records import ChunkIndex

        data = b"".join(pending.data)  # copies without the GIL from 1 MiB on
        if self._chunk_indexes:
            self._start_time = min(self._start_time, pending.start)
            self._end_time = max(self._end_time, pending.end)
        else:
            self._start_time, self._end_time = pending.start, pending.end
        packed = self._compress(data) if self._compress is not None else data
        name = self.compression.encode()
        head = _CHUNK_HEAD.pack(
            0x06,
            8 + 8 + 8 + 4 + 4 + len(name) + 8 + len(packed),
            pending.start,
            pending.end,
            len(data),
            zlib.crc32(data),
            len(name),
        )
        offset = self._f.tell()
        self._f.write(head + name + _U64.pack(len(packed)))
        self._f.write(packed)
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=pending.start,
                message_end_time=pending.end,
                chunk_start_offset=offset,
                chunk_length=len(head) + len(name) + 8 + len(packed),
                message_index_offsets={},
                message_index_length=0,
                compression=self.compression,
                compressed_size=len(packed),
                uncompressed_size=len(data),
            )
        )

    def close_chunk(self) -> None:
        """Compress and write the open chunk, if it holds any message."""
        pending = self.take_chunk()
        if pending is not None:
            self.write_chunk(pending)

    def flush(self) -> None:
        """Close the open chunk and hand everything to the operating system."""
        self.close_chunk()
        self._f.flush()

    def finish(self) -> None:
        """Write the summary section (as ``mcap.writer.Writer.finish`` lays it out) and footer."""
        from mcap.data_stream import RecordBuilder
        from mcap.opcode import Opcode
        from mcap.records import DataEnd, Footer, Statistics, SummaryOffset

        self.close_chunk()
        DataEnd(data_section_crc=0).write(self._rb)
        self._emit()
        summary_start = self._f.tell()
        b = RecordBuilder()
        offsets: list[SummaryOffset] = []
        stats = Statistics(
            message_count=sum(self._counts.values()),
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=len(self._attachment_indexes),
            metadata_count=len(self._metadata_indexes),
            chunk_count=len(self._chunk_indexes),
            message_start_time=self._start_time,
            message_end_time=self._end_time,
            channel_message_counts=dict(self._counts),
        )
        groups = (
            (Opcode.SCHEMA, self._schemas),
            (Opcode.CHANNEL, self._channels),
            (Opcode.STATISTICS, [stats]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes),
            (Opcode.ATTACHMENT_INDEX, self._attachment_indexes),
            (Opcode.METADATA_INDEX, self._metadata_indexes),
        )
        for opcode, records in groups:
            start = b.count
            for record in records:
                record.write(b)
            offsets.append(SummaryOffset(opcode, summary_start + start, b.count - start))
        offset_start = summary_start + b.count
        for offset in offsets:
            offset.write(b)
        summary = b.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), crc)
        self._f.write(summary)
        Footer(
            summary_start=summary_start, summary_offset_start=offset_start, summary_crc=crc
        ).write(self._rb)
        self._emit()
        self._f.write(MCAP_MAGIC)
        self._f.flush()


class McapSink(SinkBase):
    """Write records and raw chunks to an MCAP file (see the module docstring)."""

    def __init__(
        self,
        path: str | Path,
        ctx: SinkContext,
        *,
        flush_every: float = FLUSH_EVERY,
        chunk_size: int = 1 << 20,
    ) -> None:
        self.path = Path(path)
        self.ctx = ctx
        self.view: View = ctx.view
        self.flush_every = flush_every
        self._file: IO[bytes] = open(self.path, "wb")
        self._writer = McapFileWriter(self._file, chunk_size=chunk_size)
        self._chunk_size = chunk_size
        self._append = self._writer.append
        self._lock = threading.Lock()  # the writer thread takes idle chunks too
        self._chunks: queue.Queue[PendingChunk | None] = queue.Queue(maxsize=4)
        #: chunks and (record, its read --json line or object), in order, waiting to
        #: become messages in the open chunk: appended without the lock (one atomic
        #: list append), made into messages and moved in batches under it
        #: (McapFileWriter.take_from with _make_messages)
        self._pending: list[Any] = []
        self._batch = max(1, min(_BATCH, chunk_size >> 12))
        self._error: BaseException | None = None
        self._error_raised = False
        self._closed = False
        self._source = ctx.source
        self._raw_prefix: dict[tuple[int, Direction], bytes] = {}
        self._tails: dict[int, bytes] = {}
        self._file_json = _json_str(ctx.source).encode()
        self._counts: dict[str, int] = dict.fromkeys(
            ("noise_bytes", "crc_errors", "chunks", "bytes"), 0
        )
        self._kinds: dict[RecordKind, int] = dict.fromkeys(RecordKind, 0)
        self._next_stats = 0.0
        self._last_ts: float | None = None
        try:
            self._start(ctx)
        except BaseException:
            self._file.close()
            raise
        self._last_flush = time.monotonic()
        self._worker = threading.Thread(target=self._work, name="mbmon-mcap-writer", daemon=True)
        self._worker.start()

    def _start(self, ctx: SinkContext) -> None:
        """Header, schemas, channels, metadata and profile attachments, on disk at once."""
        w = self._writer
        w.start(library=f"mbmon {__version__}")
        self._channels: dict[str, int] = {}
        for topic, name in TOPIC_SCHEMAS.items():
            schema_id = w.register_schema(name, "jsonschema", schema_text(name))
            self._channels[topic] = w.register_channel(topic, "json", schema_id)
        self._ch_raw = self._channels[TOPIC_RAW]
        self._ch_frames = self._channels[TOPIC_FRAMES]
        self._ch_monitor = self._channels[TOPIC_MONITOR]
        self._ch_state = self._channels[TOPIC_STATE]
        self._ch_commands = self._channels[TOPIC_COMMANDS]
        self._ch_events = self._channels[TOPIC_EVENTS]
        #: messages per channel whose heads this sink packed (the writer is told on close)
        self._messages: dict[int, int] = dict.fromkeys(self._channels.values(), 0)
        self._slow_frames = 0  # frame records that took _obj_messages
        self._topic_of = {
            RecordKind.REQUEST: self._ch_frames,
            RecordKind.RESPONSE: self._ch_frames,
            RecordKind.EXCEPTION: self._ch_frames,
            RecordKind.NOISE: self._ch_frames,
            RecordKind.EVENT: self._ch_events,
            RecordKind.COMMAND: self._ch_commands,
        }
        now_ns = time.time_ns()
        w.add_metadata(
            METADATA_NAME,
            {
                "version": __version__,
                "command_line": json.dumps(list(ctx.command_line), ensure_ascii=False),
                "source": ctx.source,
                "profiles": json.dumps([name for name, _ in ctx.profiles], ensure_ascii=False),
                "profile_bindings": json.dumps(
                    profile_bindings(ctx.profile_specs, ctx.profiles), ensure_ascii=False
                ),
                "profile_specs": json.dumps(list(ctx.profile_specs), ensure_ascii=False),
                "timeout": json.dumps(ctx.timeout),
                "baud": json.dumps(ctx.baud),
                "robot": ctx.view.robot or "",
                "robot_is_client": "true" if ctx.view.robot_is_client else "false",
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(now_ns / 1e9)),
            },
        )
        for name, text in ctx.profiles:
            w.add_attachment(
                create_time=0,
                log_time=now_ns,
                name=name if name.endswith(".toml") else f"{name}.toml",
                media_type=PROFILE_MEDIA_TYPE,
                data=text.encode("utf-8"),
            )
        self._file.flush()

    # ------------------------------------------------------------------ sink API

    def on_chunk(self, chunk: Chunk) -> None:
        """One captured chunk on /modbus/raw (made into its message with the next batch)."""
        self._pending.append(chunk)

    def on_record(self, record: Record) -> None:
        """Write the messages of one record on their topics.

        What depends on the view is made here, in the calling thread: the
        ``read --json`` line of a frame record (by :func:`record_json_bytes`,
        from cached parts) or the object of another record. The messages are
        made from it in batches, by :meth:`_make_messages`.
        """
        pending = self._pending
        if record.frame is not None:
            pending.append((record, record_json_bytes(record, self.view)))
            if len(pending) < self._batch:
                return
        else:  # events, noise, commands: few, and written out at once
            pending.append((record, record_to_json(record, self.view)))
        self._move()

    def _make_messages(self, items: list[Any]) -> tuple[list[bytes], int, int]:
        """The message records of waiting chunks and records (one or more bytes per item,
        in order) and their first and last log time. Runs with the lock held (in
        either thread).

        A frame record's /modbus/frames message is its ``read --json`` line and its
        /modbus/monitor message takes the line's JSON-escaped text cut out of that
        line; other records go through :meth:`_obj_messages`. This is the writer's
        per-record work, so it is one loop with the sink's state in locals, and what
        depends on the capture time alone (log time, the monitor's timestamp) is
        made once per distinct time: a chunk and the records it completes share it.
        """
        out: list[bytes] = []
        append = out.append
        pack = _MESSAGE_HEAD.pack
        first = last = -1
        kinds, tails, raw_prefix = self._kinds, self._tails, self._raw_prefix
        ch_frames, ch_monitor, ch_raw = self._ch_frames, self._ch_monitor, self._ch_raw
        n_chunks = n_bytes = 0
        last_ts: float | None = None
        time_of = log_time = 0  # the capture time whose log time and stamp are below
        next_stats = self._next_stats
        stamp = b""
        for item in items:
            if type(item) is not tuple:  # a Chunk, on /modbus/raw
                ts = item.ts
                if ts != time_of:  # _ns(ts), inline
                    log_time = round(ts * 1_000_000) * 1000 if ts > 0.0 else 0
                    time_of, stamp = ts, b""
                stream = item.stream
                prefix = raw_prefix.get((stream.id, item.direction))
                if prefix is None:
                    prefix = self._raw_prefix_of(item)
                raw = item.data
                body = _RAW_BODY % (prefix, _float_json(ts), b2a_base64(raw, newline=False))
                n_chunks += 1
                n_bytes += len(raw)
                append(pack(5, 22 + len(body), ch_raw, 0, log_time, log_time) + body)
            else:
                record, payload = item
                ts = last_ts = record.ts
                if ts != time_of:
                    time_of, log_time, stamp = ts, _ns(ts), b""
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
                    append(self._obj_messages(record, payload, log_time))
                    next_stats = self._next_stats
                else:
                    kind = record.kind
                    kinds[kind] += 1  # also the count of its two messages (told on close)
                    if not stamp:
                        stamp = _MONITOR_STAMP % divmod(log_time, 1_000_000_000)
                    crc_error = False
                    if kind is _EXCEPTION:
                        monitor = _MONITOR_WARNING
                    elif (
                        frame.crc_ok is False
                        or frame.pdu.malformed
                        or (kind is _RESPONSE and record.request is None)  # unsolicited
                    ):
                        monitor = _MONITOR_WARNING
                        crc_error = frame.crc_ok is False and kind is _RESPONSE
                    else:
                        monitor = _MONITOR_INFO
                    tail = tails.get(frame.stream.id)
                    if tail is None:
                        tail = self._tail(frame.stream)
                    monitor %= (stamp, payload[start:end], tail, record.index)
                    n = len(payload)
                    out += (
                        pack(5, 22 + n, ch_frames, 0, log_time, log_time),
                        payload,
                        pack(5, 22 + len(monitor), ch_monitor, 0, log_time, log_time),
                        monitor,
                    )
                    if crc_error:
                        self._counts["crc_errors"] += 1
                        append(self._head(self._ch_events, log_time, n) + payload)
                    if record.state is not None:
                        append(self._state_message(record, log_time))
                    if ts >= next_stats:
                        self._add_chunk_counts(n_chunks, n_bytes)
                        n_chunks = n_bytes = 0
                        append(self._due_stats(ts, log_time))
                        next_stats = self._next_stats
            if first < 0:
                first = last = log_time
            elif log_time < first:
                first = log_time
            elif log_time > last:
                last = log_time
        self._add_chunk_counts(n_chunks, n_bytes)
        if last_ts is not None:
            self._last_ts = last_ts
        return out, first, last

    def _add_chunk_counts(self, chunks: int, size: int) -> None:
        counts = self._counts
        counts["chunks"] += chunks  # also the count of their messages (told on close)
        counts["bytes"] += size

    def _raw_prefix_of(self, chunk: Chunk) -> bytes:
        """The JSON of a chunk message up to its ``ts`` value, cached by stream direction."""
        prefix = encode({"type": "chunk", **_stream_fields(chunk.stream)}).decode()[:-1]
        text = f'{prefix},"direction":"{_DIRECTIONS[chunk.direction]}","ts":'.encode()
        self._raw_prefix[(chunk.stream.id, chunk.direction)] = text
        return text

    def _obj_messages(self, record: Record, obj: Mapping[str, Any], log_time: int) -> bytes:
        """The message records of a record made from its ``read --json`` object (noise,
        events, commands: few records, so the plain encoder does)."""
        ts = record.ts
        kind = record.kind
        self._kinds[kind] += 1
        if kind in _FRAME_KINDS:
            self._slow_frames += 1  # its messages are counted by _head
        payload = encode(obj)
        head = self._head
        n = len(payload)
        parts = [head(self._topic_of[kind], log_time, n), payload]
        if kind is RecordKind.NOISE:
            parts += (head(self._ch_events, log_time, n), payload)
            if record.noise is not None:
                self._counts["noise_bytes"] += len(record.noise.raw)
                if "crc" in record.noise.reason.lower():
                    self._counts["crc_errors"] += 1
        elif kind is RecordKind.EVENT:
            event = record.event
            if event is not None and event.kind in SOURCE_EVENTS:
                raw = self._raw_event(event)
                parts += (head(self._ch_raw, log_time, len(raw)), raw)
        elif kind is RecordKind.RESPONSE and obj["crc_ok"] is False:
            self._counts["crc_errors"] += 1
            parts += (head(self._ch_events, log_time, n), payload)
        stream = record.stream
        tail = self._tails.get(stream.id if stream is not None else -1)
        if tail is None:
            tail = self._tail(stream)
        sec, nsec = divmod(log_time, 1_000_000_000)
        monitor = _MONITOR % (
            sec, nsec, log_level(record, obj), _json_str(obj["line"]).encode(), tail, record.index
        )  # fmt: skip
        parts += (head(self._ch_monitor, log_time, len(monitor)), monitor)
        if record.state is not None:
            parts.append(self._state_message(record, log_time))
        if ts >= self._next_stats:
            parts.append(self._due_stats(ts, log_time))
        return b"".join(parts)

    def _tail(self, stream: Stream | None) -> bytes:
        """The end of a stream's monitor messages (name, file, "line" key), cached by stream id
        (a Stream hashes slowly); -1 stands for records of no stream."""
        tail = _MONITOR_TAIL % (_json_str(stream_name(stream)).encode(), self._file_json)
        self._tails[stream.id if stream is not None else -1] = tail
        return tail

    def _head(self, channel_id: int, log_time: int, size: int) -> bytes:
        """The head of a message record of ``size`` data bytes on a channel (and count it)."""
        self._messages[channel_id] += 1
        return _MESSAGE_HEAD.pack(5, 22 + size, channel_id, 0, log_time, log_time)

    def _state_message(self, record: Record, log_time: int) -> bytes:
        """The /hrss/state message record of a record that carries robot state."""
        state: dict[str, Any] = {"time": record.ts, "index": record.index}
        for key, value in (record.state or {}).items():
            if isinstance(value, bool):
                state[key] = int(value)
            elif isinstance(value, int | float) and math.isfinite(value):
                state[key] = value  # flat numbers only: NaN/inf have no JSON form
        data = encode(state)
        return self._head(self._ch_state, log_time, len(data)) + data

    def _due_stats(self, ts: float, log_time: int) -> bytes:
        """The stats message record due at ``ts`` (none for the first record)."""
        data = b""
        if self._next_stats > 0:
            stats = self._stats(ts)
            data = self._head(self._ch_events, log_time, len(stats)) + stats
        self._next_stats = ts + STATS_EVERY
        return data

    def close(self) -> None:
        """Write what is left and finish the file (summary, index, footer).

        SIGINT/SIGTERM are held back meanwhile: a second Ctrl-C cannot leave
        the file unfinished.
        """
        if self._closed:
            return
        self._closed = True
        old = _block_signals()
        try:
            with self._lock:
                self._writer.take_from(self._pending, self._make_messages)
                if self._last_ts is not None:
                    stats = self._stats(self._last_ts, True)
                    self._append(self._ch_events, _ns(self._last_ts), stats)
                messages = self._messages
                messages[self._ch_raw] += self._counts["chunks"]
                fast = sum(self._kinds[k] for k in _FRAME_KINDS) - self._slow_frames
                messages[self._ch_frames] += fast
                messages[self._ch_monitor] += fast
                for channel_id, count in messages.items():
                    self._writer.count(channel_id, count)
                pending = self._writer.take_chunk()
                if pending is not None:
                    self._chunks.put(pending)
                self._chunks.put(None)
            self._worker.join()
            if self._error is None:
                self._writer.finish()
        finally:
            try:
                self._file.close()
            finally:
                _restore_signals(old)
        self._raise_error()

    # ------------------------------------------------------------------ internals

    def _move(self) -> None:
        """Move the waiting message records into the open chunk; hand it on when full or due."""
        if self._error is not None:
            self._raise_error()
        with self._lock:
            size = self._writer.take_from(self._pending, self._make_messages)
            if size > self._chunk_size or time.monotonic() - self._last_flush >= self.flush_every:
                pending = self._writer.take_chunk()
                self._last_flush = time.monotonic()
                if pending is not None:
                    # under the lock: chunks reach the writer thread in order; blocks
                    # (back pressure) when it is four chunks behind
                    self._chunks.put(pending)

    def _raise_error(self) -> None:
        if self._error is not None and not self._error_raised:
            self._error_raised = True
            error = self._error
            raise SinkError(f"{self.path}: cannot write: {error}") from error

    def _work(self) -> None:
        """Writer thread: compress and write chunks (zstd and the file release the GIL, so
        this overlaps with decoding), and close the open chunk when records stop coming."""
        tick = max(0.05, self.flush_every / 4)
        chunks = self._chunks
        while True:
            try:
                pending = chunks.get(timeout=tick)
            except queue.Empty:
                if time.monotonic() - self._last_flush < self.flush_every:
                    continue
                with self._lock:
                    if not chunks.empty():
                        continue  # write the older chunks first
                    self._writer.take_from(self._pending, self._make_messages)
                    pending = self._writer.take_chunk()
                    self._last_flush = time.monotonic()
                if pending is None:
                    continue
            if pending is None:
                return
            if self._error is not None:
                continue  # after a write error: drain, so the writing thread never blocks
            try:
                self._writer.write_chunk(pending)
                self._file.flush()
            except Exception as exc:  # disk full, I/O error: reported on the next write
                self._error = exc

    def _raw_event(self, event: Event) -> bytes:
        body = {
            "type": "event",
            **_stream_fields(event.stream),
            "ts": event.ts,
            "direction": None,
            "data": "",
            "event": event.kind.value,
            "info": dict(event.info),
        }
        return encode(body)

    def _stats(self, ts: float, final: bool = False) -> bytes:
        """The writer's own counters as an /mbmon/events message (index null)."""
        kinds = self._kinds
        info: dict[str, Any] = {
            "records": sum(kinds.values()),
            "requests": kinds[RecordKind.REQUEST],
            "responses": kinds[RecordKind.RESPONSE],
            "exceptions": kinds[RecordKind.EXCEPTION],
            "noise": kinds[RecordKind.NOISE],
            "events": kinds[RecordKind.EVENT],
            "commands": kinds[RecordKind.COMMAND],
            **self._counts,
        }
        if final:
            info["final"] = True
        line_ts = time.strftime("%H:%M:%S", time.localtime(ts))
        obj: dict[str, Any] = {
            "index": None, "time": ts, "stream": None, "src": None, "dst": None,
            "transport": None, "tid": None, "unit": None, "fc": None, "kind": "event",
            "exception_code": None, "address": None, "count": None, "values": None,
            "pdu": None, "line": "", "notes": None, "crc_ok": None, "latency_ms": None,
            "malformed": None, "request_index": None, "event": "stats", "info": info,
        }  # fmt: skip
        obj["line"] = f"{line_ts}  -- Stats: " + ", ".join(f"{k}={v}" for k, v in info.items())
        return encode(obj)


def _block_signals() -> set[signal.Signals] | None:
    if threading.current_thread() is not threading.main_thread():
        return None  # Python runs signal handlers in the main thread only
    try:
        return signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    except (AttributeError, OSError, ValueError):  # platforms without pthread_sigmask
        return None


def _restore_signals(old: set[signal.Signals] | None) -> None:
    if old is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
