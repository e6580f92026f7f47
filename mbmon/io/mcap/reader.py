"""Tolerant reader for the MCAP logs mbmon writes.

A finished file (footer, summary and chunk index present) is read through its
chunk index. A file that was never finished (the process was killed, the disk
filled up) is read linearly: every complete chunk is recovered, and
:attr:`McapLog.status` says how many messages came back and at which byte the
read stopped. Bytes that are not MCAP raise :class:`LogError`; a chunk that
fails its CRC, does not decompress or does not parse is passed over, the chunks
after it are read, and :class:`LogError` names it by its offset at the end;
never a traceback from the ``mcap`` package. Payloads are the readers' to
judge (:func:`mbmon.io.replay.payload`): a damaged one is left out and
recorded with where it is (:meth:`McapLog.skip`, :attr:`ReadStatus.skipped`).

Messages are yielded in file order, which is the order mbmon wrote them (the
order of records on the console), not re-sorted by log time.
"""

from __future__ import annotations

import io
import json
import struct
import zlib
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

from mbmon.io.mcap.proto import DECODERS

MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER = 0x01
_OP_FOOTER = 0x02
_OP_SCHEMA = 0x03
_OP_CHANNEL = 0x04
_OP_MESSAGE = 0x05
_OP_CHUNK = 0x06
_OP_ATTACHMENT = 0x09
_OP_METADATA = 0x0C
_OP_DATA_END = 0x0F
_FOOTER_RECORD = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, crc
_MAX_RECORD = 1 << 31  # no record mbmon writes comes near this; larger lengths mean damage
#: the largest uncompressed chunk believed (mbmon writes about 1 MiB): a larger size
#: field is damage, found before anything is allocated or decompressed
_MAX_CHUNK_DATA = 1 << 28

_REC_HEAD = struct.Struct("<BQ")
_MSG_HEAD = struct.Struct("<HIQQ")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


class LogError(Exception):
    """A log that cannot be read (not MCAP, corrupt chunk, unreadable file)."""


def _not_json(constant: str) -> Any:
    raise ValueError(f"{constant} is not a JSON number")


#: one decoder for every payload (``json.loads`` with an option builds one per call)
_decode_json = json.JSONDecoder(parse_constant=_not_json).decode


@dataclass(frozen=True, slots=True)
class LogMessage:
    """One message as stored: topic, capture times in ns, and its JSON payload.

    ``chunk`` is the file offset of the chunk (or the record) that holds it and
    ``at`` the message record's offset among the chunk's records: where it is,
    for a report of damage (:meth:`McapLog.skip`).
    """

    topic: str
    log_time: int
    publish_time: int
    sequence: int
    raw: bytes
    chunk: int = 0
    at: int = 0
    #: the payload's decoder when it is not JSON (log format 3's protobuf messages):
    #: gives the object a format-2 log holds, or raises ``ValueError``
    decoder: Callable[[bytes], Any] | None = None

    def json(self) -> Any:
        """Decode the payload to its JSON object (a protobuf message of format 3 to the
        object format 2 stores); a payload that is not JSON (or nests deeper than a
        parser goes, or holds NaN), or not a valid message of its protobuf schema, is a
        :class:`LogError` that says where the message is."""
        value, why = self.decode()
        if why is not None:
            raise LogError(f"{self.where()}: {why}")
        return value

    def decode(self) -> tuple[Any, str | None]:
        """``(payload, None)``, or ``(None, why)`` when the payload is not valid JSON (or
        not a valid message of its protobuf schema)."""
        if self.decoder is not None:
            try:
                return self.decoder(self.raw), None
            except ValueError as exc:
                return None, f"not a valid protobuf message: {exc}"
        try:
            return _decode_json(self.raw.decode()), None
        except RecursionError:
            return None, "not valid JSON: nested too deeply"
        except ValueError as exc:
            return None, f"not valid JSON: {exc}"

    def where(self) -> str:
        """Where the message is in its file, in words."""
        return f"message on {self.topic} at byte {self.at} of the chunk at byte {self.chunk}"


@dataclass(frozen=True, slots=True)
class LogAttachment:
    """An attachment record (mbmon stores the profile TOML files in force)."""

    name: str
    media_type: str
    data: bytes
    log_time: int


@dataclass(slots=True)
class ReadStatus:
    """How far reading a log got.

    ``finished``: the file has a footer and was read through its chunk index.
    ``messages``: messages delivered so far (after a full pass: all recovered).
    ``stopped_at``: byte offset where a linear read stopped because the rest is
    missing or damaged (``None`` if the file ended cleanly).
    ``problem``: why it stopped, in words.
    """

    finished: bool
    file_size: int
    messages: int = 0
    stopped_at: int | None = None
    problem: str | None = None
    #: messages whose payload is damaged, left out by the readers (:meth:`McapLog.skip`):
    #: (chunk offset, record offset) -> why
    skipped: dict[tuple[int, int], str] = field(default_factory=dict)

    def describe(self) -> str:
        """One line for the user about the state of the file."""
        if self.finished:
            return f"finished log, {self.messages} messages"
        where = f"stopped at byte {self.stopped_at} of {self.file_size}"
        why = f" ({self.problem})" if self.problem else ""
        return f"log was not finished: recovered {self.messages} messages, {where}{why}"

    def skipped_lines(self, most: int = 5) -> list[str]:
        """The damaged messages left out, for the user: a count, and the first few."""
        if not self.skipped:
            return []
        n = len(self.skipped)
        lines = [f"{n} damaged message{'s' if n != 1 else ''} left out (everything else shown):"]
        lines += [f"  {why}" for why in list(self.skipped.values())[:most]]
        if n > most:
            lines.append(f"  ... {n - most} more")
        return lines


@dataclass(slots=True)
class _Channel:
    id: int
    topic: str
    schema_id: int
    encoding: str


@dataclass(slots=True)
class _Span:
    """A top-level chunk found by the index or by the linear pre-scan."""

    offset: int
    length: int
    channels: frozenset[int] | None = None  # channel ids inside, when the index says


@dataclass(slots=True)
class _Layout:
    header_end: int = 0
    chunks: list[_Span] = field(default_factory=list)
    loose: list[tuple[int, int, int]] = field(default_factory=list)  # (opcode, offset, len)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: list[LogAttachment] = field(default_factory=list)
    channels: dict[int, _Channel] = field(default_factory=dict)
    schemas: dict[int, tuple[str, str, bytes]] = field(default_factory=dict)
    stats_counts: dict[int, int] | None = None
    stats_span: tuple[int, int] | None = None
    stopped_at: int | None = None
    problem: str | None = None


class McapLog:
    """An mbmon MCAP log opened for reading; use as a context manager.

    Opening reads the layout (index when finished, else a linear scan of the
    record headers) plus metadata and attachments; :meth:`messages` then reads
    the chunks.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.status = ReadStatus(finished=False, file_size=0)  # filled in once the layout is read
        try:
            self._f: BinaryIO = open(self.path, "rb")
        except OSError as exc:
            raise LogError(f"{self.path}: cannot open: {exc.strerror or exc}") from None
        try:
            self.size = self._f.seek(0, io.SEEK_END)
            self._f.seek(0)
            head = self._f.read(len(MAGIC))
            if head != MAGIC:
                what = "empty file" if not head else "not an MCAP file (bad magic)"
                raise LogError(f"{self.path}: {what}")
            layout = self._read_index()
            self.finished = layout is not None
            if layout is None:
                layout = self._scan()
        except LogError:
            self._f.close()
            raise
        except OSError as exc:
            self._f.close()
            raise LogError(f"{self.path}: read error: {exc}") from None
        self._layout = layout
        #: ``progress(bytes done, file size)`` after each chunk :meth:`messages` reads
        #: (a progress bar for big logs), or ``None``
        self.progress: Callable[[int, int], None] | None = None
        self.metadata: dict[str, dict[str, str]] = layout.metadata
        self.attachments: list[LogAttachment] = layout.attachments
        self.status.finished, self.status.file_size = self.finished, self.size
        self.status.stopped_at, self.status.problem = layout.stopped_at, layout.problem

    # -- public -----------------------------------------------------------

    def __enter__(self) -> McapLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._f.close()

    @property
    def topics(self) -> dict[str, int]:
        """Message count per topic from the statistics record (finished files only)."""
        counts = self._layout.stats_counts or {}
        return {ch.topic: counts.get(ch.id, 0) for ch in self._layout.channels.values()}

    @property
    def time_span(self) -> tuple[int, int] | None:
        """(first, last) log time in ns from the statistics record, if finished."""
        return self._layout.stats_span

    def schema_of(self, topic: str) -> tuple[str, str, bytes] | None:
        """(name, encoding, data) of the schema of ``topic``, once its channel was seen."""
        for ch in self._layout.channels.values():
            if ch.topic == topic:
                return self._layout.schemas.get(ch.schema_id)
        return None

    def profiles(self) -> list[tuple[str, str]]:
        """The profile TOML files recorded with the log, as (name, text)."""
        out = []
        for att in self.attachments:
            if att.media_type == "application/toml" or att.name.endswith(".toml"):
                out.append((att.name, att.data.decode("utf-8", "replace")))
        return out

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[LogMessage]:
        """Yield messages in file order, optionally only those on ``topics``.

        After the generator is exhausted, :attr:`status` holds the count of
        messages recovered from the chunks read, on every topic (so a read of
        some topics reports what a read of all would). A damaged chunk (cut,
        not decompressing, failing its CRC, records that do not parse) is
        passed over, the chunks after it are read, and at the end
        :class:`LogError` names the first damaged chunk by its offset (and how
        many more there were), after every readable message was yielded.
        """
        wanted = set(topics) if topics is not None else None
        layout = self._layout
        self.status.messages = 0
        channels = layout.channels
        wanted_ids: set[int] | None = None
        damage: list[str] = []
        for span in layout.chunks:
            if wanted is not None and span.channels is not None:
                if wanted_ids is None or len(wanted_ids) < len(channels):
                    wanted_ids = {c.id for c in channels.values() if c.topic in wanted}
                if not (span.channels & wanted_ids):
                    continue
            status = self.status
            try:
                data = self._chunk_records(span)
                for msg in self._parse_records(data, span.offset):
                    status.messages += 1
                    if wanted is not None and msg.topic not in wanted:
                        continue
                    yield msg
            except LogError as exc:
                damage.append(str(exc))
            if self.progress is not None:
                self.progress(span.offset + span.length, self.size)
        if damage:
            more = len(damage) - 1
            also = f" (and {more} more damaged chunk{'s' if more > 1 else ''})" if more else ""
            raise LogError(
                f"{self.path}: {damage[0]}{also}; {self.status.messages} messages read, "
                "everything readable shown"
            )

    # -- layout -----------------------------------------------------------

    def _read_index(self) -> _Layout | None:
        """Read the summary of a finished file; ``None`` if there is none usable."""
        summary_start = self._summary_start()
        if summary_start is None:
            return None
        try:
            return self._summary_layout(summary_start)
        except Exception:  # a damaged summary: fall back to the linear read
            return None

    def _summary_start(self) -> int | None:
        """Where the summary starts, from a footer that is whole and whose summary passes
        its CRC (when it has one); ``None`` when the file has no such footer."""
        f = self._f
        if self.size < 2 * len(MAGIC) + _FOOTER_RECORD:
            return None
        f.seek(self.size - len(MAGIC))
        if f.read(len(MAGIC)) != MAGIC:
            return None
        f.seek(self.size - len(MAGIC) - _FOOTER_RECORD)
        foot = f.read(_FOOTER_RECORD)
        op, length = _REC_HEAD.unpack_from(foot)
        if op != _OP_FOOTER or length != 20:
            return None
        summary_start, offset_start = _U64.unpack_from(foot, 9)[0], _U64.unpack_from(foot, 17)[0]
        summary_crc = _U32.unpack_from(foot, 25)[0]
        footer_at = self.size - len(MAGIC) - _FOOTER_RECORD
        if not len(MAGIC) < summary_start <= footer_at or offset_start > footer_at:
            return None
        if summary_crc:  # a damaged summary is not trusted: the linear read takes over
            f.seek(summary_start)
            crc = zlib.crc32(f.read(footer_at - summary_start))
            crc = zlib.crc32(foot[: 1 + 8 + 8 + 8], crc)
            if crc != summary_crc:
                return None
        return summary_start

    def _summary_layout(self, summary_start: int) -> _Layout | None:
        """The layout the summary gives, ``None`` when it does not match the file; any
        exception means a damaged summary (the ``mcap`` package parses it)."""
        from mcap.reader import SeekingReader

        f = self._f
        f.seek(0)
        reader = SeekingReader(f, validate_crcs=True)
        summary = reader.get_summary()
        if summary is None or not summary.chunk_indexes:
            return None
        layout = _Layout()
        for ch in summary.channels.values():
            layout.channels[ch.id] = _Channel(ch.id, ch.topic, ch.schema_id, ch.message_encoding)
        for sc in summary.schemas.values():
            layout.schemas[sc.id] = (sc.name, sc.encoding, sc.data)
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            if not self._is_record(ci.chunk_start_offset, ci.chunk_length, summary_start,
                                   _OP_CHUNK):  # fmt: skip
                return None  # an index that does not match the file
            ids = frozenset(ci.message_index_offsets) if ci.message_index_offsets else None
            layout.chunks.append(_Span(ci.chunk_start_offset, ci.chunk_length, ids))
        for ai in summary.attachment_indexes:
            if not self._is_record(ai.offset, ai.length, summary_start, _OP_ATTACHMENT):
                return None
        for mi in summary.metadata_indexes:
            if not self._is_record(mi.offset, mi.length, summary_start, _OP_METADATA):
                return None
        if summary.statistics is not None:
            st = summary.statistics
            layout.stats_counts = dict(st.channel_message_counts)
            if st.message_count:
                layout.stats_span = (st.message_start_time, st.message_end_time)
        for md in reader.iter_metadata():
            layout.metadata[md.name] = dict(md.metadata)
        for att in reader.iter_attachments():
            layout.attachments.append(
                LogAttachment(att.name, att.media_type, bytes(att.data), att.log_time)
            )
        return layout

    def _is_record(self, offset: int, length: int, end: int, opcode: int) -> bool:
        """Whether an index entry points at a whole record of that opcode before ``end``."""
        if not len(MAGIC) <= offset or length < 9 or offset + length > end:
            return False
        self._f.seek(offset)
        head = self._f.read(9)
        if len(head) != 9:
            return False
        op, body = _REC_HEAD.unpack(head)
        return op == opcode and body == length - 9

    def _scan(self) -> _Layout:
        """Walk the top-level records of an unfinished file without decompressing chunks."""
        f = self._f
        layout = _Layout()
        pos = len(MAGIC)
        size = self.size
        f.seek(pos)
        while True:
            if pos == size:
                layout.stopped_at, layout.problem = pos, "file ends without a summary and footer"
                break
            if size - pos < 9:
                layout.stopped_at, layout.problem = pos, "record header cut off"
                break
            head = f.read(9)
            op, length = _REC_HEAD.unpack(head)
            body_at = pos + 9
            if op == 0 and length == 0:
                layout.stopped_at, layout.problem = pos, "zero bytes (file not completely written)"
                break
            if length > _MAX_RECORD or body_at + length > size:
                layout.stopped_at = pos
                layout.problem = (
                    f"record (opcode 0x{op:02X}) cut off at end of file: it claims "
                    f"{length} bytes, {size - body_at} remain"
                )
                break
            if op == _OP_HEADER and pos == len(MAGIC):
                layout.header_end = body_at + length
            elif op == _OP_CHUNK:
                layout.chunks.append(_Span(pos, 9 + length))
            elif op in (_OP_METADATA, _OP_ATTACHMENT, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE):
                body = f.read(length)
                try:
                    self._loose_record(layout, op, body, pos)
                except LogError:
                    layout.stopped_at, layout.problem = pos, "damaged record"
                    break
            elif op in (_OP_DATA_END, _OP_FOOTER):
                # the summary section follows but the file was cut inside it
                layout.stopped_at, layout.problem = pos, "summary section incomplete"
                break
            elif op == 0 or 0x10 <= op < 0x80:
                layout.stopped_at = pos
                layout.problem = f"invalid record opcode 0x{op:02X}"
                break
            pos = body_at + length
            f.seek(pos)
        return layout

    def _loose_record(self, layout: _Layout, op: int, body: bytes, pos: int) -> None:
        from mcap.data_stream import ReadDataStream
        from mcap.records import Attachment, Metadata

        try:
            if op == _OP_METADATA:
                md = Metadata.read(ReadDataStream(io.BytesIO(body)))
                layout.metadata[md.name] = dict(md.metadata)
            elif op == _OP_ATTACHMENT:
                att = Attachment.read(ReadDataStream(io.BytesIO(body)))
                layout.attachments.append(
                    LogAttachment(att.name, att.media_type, bytes(att.data), att.log_time)
                )
            else:
                # schemas, channels and messages outside chunks: parse with the chunk parser
                layout.loose.append((op, pos, len(body)))
                record = _REC_HEAD.pack(op, len(body)) + body
                for _ in self._parse_records(record, pos, layout):
                    pass
        except LogError:
            raise
        except Exception as exc:
            raise LogError(f"damaged record at byte {pos}: {exc}") from None

    # -- chunks -----------------------------------------------------------

    def _chunk_records(self, span: _Span) -> bytes:
        """Read, decompress and CRC-check one chunk; its inner records as bytes."""
        f = self._f
        where = f"chunk at byte {span.offset}"
        if span.length < 9 or span.offset + span.length > self.size:  # before reading it
            raise self._damage(span.offset, f"{where}: length {span.length} beyond the file")
        f.seek(span.offset)
        raw = f.read(span.length)
        if len(raw) != span.length:
            raise self._damage(span.offset, f"{where} is cut off")
        try:
            op, _length = _REC_HEAD.unpack_from(raw)
            if op != _OP_CHUNK:
                raise ValueError(f"expected a chunk record, found opcode 0x{op:02X}")
            p = 9 + 16  # message start/end time
            usize = _U64.unpack_from(raw, p)[0]
            crc = _U32.unpack_from(raw, p + 8)[0]
            p += 12
            clen = _U32.unpack_from(raw, p)[0]
            if clen > len(raw) - p - 4:
                raise ValueError(f"compression name length {clen} beyond the chunk")
            compression = raw[p + 4 : p + 4 + clen].decode()
            p += 4 + clen
            rlen = _U64.unpack_from(raw, p)[0]
            if usize > _MAX_CHUNK_DATA:
                raise ValueError(f"uncompressed size {usize} is not believable")
            if compression == "" and usize != rlen:
                raise ValueError(f"uncompressed size {usize} != records length {rlen}")
            p += 8
            if p + rlen != len(raw):  # the records are the last field: they fill the chunk
                raise ValueError(f"records length {rlen} does not fill the chunk")
            comp = raw[p : p + rlen]
        except (struct.error, UnicodeDecodeError, ValueError) as exc:
            raise self._damage(span.offset, f"{where}: {exc}") from None
        try:
            if compression == "zstd":
                import zstandard

                data = zstandard.ZstdDecompressor().decompress(comp, max_output_size=usize)
            elif compression == "lz4":
                import lz4.frame  # type: ignore[import-not-found, import-untyped, unused-ignore]

                data = lz4.frame.decompress(comp)
            elif compression == "":
                data = bytes(comp)
            else:
                raise ValueError(f"unsupported compression {compression!r}")
        except ImportError as exc:
            raise LogError(f"{where}: {compression} support missing: {exc}") from None
        except Exception as exc:
            raise self._damage(span.offset, f"{where} does not decompress: {exc}") from None
        if len(data) != usize:
            raise self._damage(span.offset, f"{where}: size {len(data)} != {usize}")
        if crc and zlib.crc32(data) != crc:
            raise self._damage(span.offset, f"{where} fails its CRC")
        return data

    def skip(self, msg: LogMessage, why: str) -> None:
        """Record that a reader left ``msg`` out because its payload is damaged (``why``);
        the same message met again by another pass over the log counts once."""
        key = (msg.chunk, msg.at)
        if key not in self.status.skipped:
            self.status.skipped[key] = f"{msg.where()}: {why}"

    def _damage(self, offset: int, why: str) -> LogError:
        """Damage at ``offset``: the first (lowest) damage of the file is its status."""
        status = self.status
        if status.stopped_at is None or offset < status.stopped_at:
            status.stopped_at, status.problem = offset, why
        return LogError(why)

    def _parse_records(
        self, data: bytes, chunk_offset: int, layout: _Layout | None = None
    ) -> Iterator[LogMessage]:
        """Parse the records inside a chunk (schemas, channels, messages)."""
        layout = layout or self._layout
        channels = layout.channels
        decoders: dict[int, Callable[[bytes], Any] | None] = {}
        view = memoryview(data)
        n = len(data)
        p = 0
        try:
            while p < n:
                op, length = _REC_HEAD.unpack_from(view, p)
                body = p + 9
                end = body + length
                if end > n:
                    raise ValueError("record runs past the end of the chunk")
                if op == _OP_MESSAGE:
                    if length < _MSG_HEAD.size:
                        raise ValueError(f"message record of {length} bytes")
                    cid, seq, log_time, pub_time = _MSG_HEAD.unpack_from(view, body)
                    ch = channels.get(cid)
                    if ch is None:
                        raise ValueError(f"message on unknown channel {cid}")
                    data = bytes(view[body + 22 : end])
                    if cid not in decoders:
                        decoders[cid] = _decoder(ch, layout)
                    yield LogMessage(
                        ch.topic, log_time, pub_time, seq, data, chunk_offset, p, decoders[cid]
                    )
                elif op == _OP_CHANNEL:
                    cid, sid = _U16.unpack_from(view, body)[0], _U16.unpack_from(view, body + 2)[0]
                    q = body + 4
                    topic, q = _string(view, q)
                    encoding, q = _string(view, q)
                    channels.setdefault(cid, _Channel(cid, topic, sid, encoding))
                elif op == _OP_SCHEMA:
                    sid = _U16.unpack_from(view, body)[0]
                    q = body + 2
                    name, q = _string(view, q)
                    encoding, q = _string(view, q)
                    dlen = _U32.unpack_from(view, q)[0]
                    layout.schemas.setdefault(
                        sid, (name, encoding, bytes(view[q + 4 : q + 4 + dlen]))
                    )
                p = end
        except (struct.error, UnicodeDecodeError, ValueError) as exc:
            raise self._damage(chunk_offset, f"chunk at byte {chunk_offset}: {exc}") from None


def _decoder(ch: _Channel, layout: _Layout) -> Callable[[bytes], Any] | None:
    """The decoder of a channel's messages: None for JSON; for protobuf, its schema's
    (log format 3), or one that says the schema is not mbmon's."""
    if ch.encoding != "protobuf":
        return None
    schema = layout.schemas.get(ch.schema_id)
    name = schema[0] if schema is not None else f"schema {ch.schema_id} (missing)"
    found = DECODERS.get(name)
    if found is not None:
        return found

    def unknown(data: bytes) -> Any:
        raise ValueError(f"{name} is not a protobuf schema mbmon reads")

    return unknown


def _string(view: memoryview, p: int) -> tuple[str, int]:
    n = _U32.unpack_from(view, p)[0]
    end = p + 4 + n
    if end > len(view):
        raise ValueError("string runs past its record")
    return str(view[p + 4 : end], "utf-8"), end


def open_log(path: str | Path) -> McapLog:
    """Open an mbmon MCAP log for reading (see :class:`McapLog`)."""
    return McapLog(path)
