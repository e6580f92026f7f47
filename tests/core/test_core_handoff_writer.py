"""The log writer packs its MCAP records itself, byte for byte as the ``mcap`` package's
record classes write them (the reference, used here and nowhere in the writing path).

A file made by :class:`McapFileWriter` (header, schemas, channels with and without
a schema, metadata, attachments, chunks of one and of several pieces, zstd and no
compression, the summary and footer) is compared, record by record, with the same
records written by ``mcap.records``; and the whole file with one laid out by the
``mcap`` package alone from the records it reads back.
"""

from __future__ import annotations

import io
import struct
import zlib
from typing import Any

import pytest
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import StreamReader

from mbmon.io.mcap import writer as writer_mod
from mbmon.io.mcap.writer import MCAP_MAGIC, MESSAGE_HEAD, McapFileWriter, PendingChunk

META = {"command": "mbmon read x.pcap -w ü.mcap", "": "", "format": "3", "ë": "€" * 40}


def _message(channel: int, t: int, data: bytes) -> bytes:
    return MESSAGE_HEAD.pack(0x05, 22 + len(data), channel, 0, t, t) + data


def _write(stream: io.BytesIO, *, compress: bool) -> McapFileWriter:
    w = McapFileWriter(stream, chunk_size=1000)
    if not compress:
        w.compression, w._compress = "", None
    w.start(library="mbmon test ü")
    s1 = w.register_schema("modbus.Frame", "protobuf", b"\x0a\x03abc" * 30)
    s2 = w.register_schema("", "", b"")
    c1 = w.register_channel("/modbus/frames", "protobuf", s1)
    c2 = w.register_channel("/mbmon/events", "json", 0)
    w.register_channel("/x/ü", "json", s2)
    w.add_metadata("mbmon", META)
    w.add_metadata("empty", {})
    w.add_attachment(0, 1_700_000_000_123_456_789, "hrss.toml", "application/toml", b"[a]\n" * 9)
    w.add_attachment(5, 0, "", "", b"")
    w.take_from([[_message(c1, 10 + i, bytes([i]) * i) for i in range(40)]], _as_records)
    w.count(c1, 40)
    w.close_chunk()  # one chunk of one piece ...
    ready: list[PendingChunk] = []
    for i in range(3):  # ... and one of several
        w.take_from([[_message(c2, 500 - i, b'{"k":%d}' % i)]], _as_records)
        w.count(c2, 1)
    w.close_chunk_into(ready)
    for chunk in ready:
        w.write_chunk(chunk)
    w.add_message(c1, 7, b"late")
    w.finish()
    return w


def _as_records(items: list[Any], state: Any) -> tuple[list[bytes], int, int, Any]:
    records = [r for item in items for r in item]
    times = [struct.unpack_from("<Q", r, 15)[0] for r in records]
    return records, min(times), max(times), state


def _records(data: bytes) -> list[tuple[int, bytes]]:
    """The file's records (opcode, whole record bytes), magic to magic."""
    assert data[:8] == MCAP_MAGIC and data[-8:] == MCAP_MAGIC
    out, at = [], 8
    while at < len(data) - 8:
        op, n = struct.unpack_from("<BQ", data, at)
        out.append((op, data[at : at + 9 + n]))
        at += 9 + n
    assert at == len(data) - 8
    return out


def _ref(record: Any) -> bytes:
    b = RecordBuilder()
    record.write(b)
    return b.end()


@pytest.mark.parametrize("compress", [True, False])
def test_records_are_the_mcap_packages(compress: bool) -> None:
    f = io.BytesIO()
    _write(f, compress=compress)
    data = f.getvalue()
    records = _records(data)
    # every record read back by the mcap package and written again by it: the same bytes
    parsed = list(StreamReader(io.BytesIO(data), skip_magic=False, emit_chunks=True).records)
    assert len(parsed) == len(records)
    for (op, raw), rec in zip(records, parsed, strict=True):
        if op == Opcode.CHUNK:
            chunk = rec  # its head as the mcap package writes it, its data as stored
            assert _ref(chunk) == raw
            assert chunk.compression == ("zstd" if compress else "")
            if not compress:
                assert chunk.uncompressed_crc == zlib.crc32(chunk.data)
        elif op == Opcode.MESSAGE:
            raise AssertionError("a message record outside a chunk")
        else:
            assert _ref(rec) == raw, f"record {op:#x}"
    by_kind: dict[str, list[Any]] = {}
    data_end = next(i for i, rec in enumerate(parsed) if isinstance(rec, DataEnd))
    for rec in parsed[:data_end]:  # the data section (the summary repeats some)
        by_kind.setdefault(type(rec).__name__, []).append(rec)
    assert [(x.id, x.name, x.encoding, x.data) for x in by_kind["Schema"]] == [
        (1, "modbus.Frame", "protobuf", b"\x0a\x03abc" * 30),
        (2, "", "", b""),
    ]
    assert [
        (x.id, x.topic, x.message_encoding, x.schema_id, x.metadata) for x in by_kind["Channel"]
    ] == [
        (1, "/modbus/frames", "protobuf", 1, {}),
        (2, "/mbmon/events", "json", 0, {}),
        (3, "/x/ü", "json", 2, {}),
    ]
    assert [(x.name, x.metadata) for x in by_kind["Metadata"]] == [("mbmon", META), ("empty", {})]
    assert [
        (x.create_time, x.log_time, x.name, x.media_type, x.data) for x in by_kind["Attachment"]
    ] == [
        (0, 1_700_000_000_123_456_789, "hrss.toml", "application/toml", b"[a]\n" * 9),
        (5, 0, "", "", b""),
    ]
    stats = next(x for x in parsed if isinstance(x, Statistics))
    assert (stats.message_count, stats.channel_message_counts) == (44, {1: 41, 2: 3, 3: 0})
    assert (stats.message_start_time, stats.message_end_time) == (7, 500)
    kinds = [type(r).__name__ for r in parsed]
    assert kinds.count("Chunk") == 3 and kinds.count("ChunkIndex") == 3
    assert kinds.count("Attachment") == 2 and kinds.count("AttachmentIndex") == 2
    assert kinds.count("Metadata") == 2 and kinds.count("MetadataIndex") == 2


@pytest.mark.parametrize("compress", [True, False])
def test_the_summary_is_laid_out_as_the_mcap_package_does(compress: bool) -> None:
    """The data section's records and the summary rebuilt from what was written, with the
    ``mcap`` package's record classes and the layout of ``mcap.writer.Writer.finish``:
    the file's every byte."""
    f = io.BytesIO()
    _write(f, compress=compress)
    data = f.getvalue()
    parsed = list(StreamReader(io.BytesIO(data), skip_magic=False, emit_chunks=True).records)
    out = RecordBuilder()
    out.write(MCAP_MAGIC)
    schemas, channels, chunk_idx, att_idx, meta_idx = [], [], [], [], []
    counts: dict[int, int] = {}
    start = end = None
    for rec in parsed:
        if isinstance(rec, DataEnd):
            break
        offset = out.count
        out.write(_ref(rec))
        length = out.count - offset
        if isinstance(rec, Header):
            assert rec.profile == "" and rec.library == "mbmon test ü"
        elif isinstance(rec, Schema):
            schemas.append(rec)
        elif isinstance(rec, Channel):
            channels.append(rec)
            counts[rec.id] = 0
        elif isinstance(rec, Metadata):
            meta_idx.append(MetadataIndex(offset=offset, length=length, name=rec.name))
        elif isinstance(rec, Attachment):
            att_idx.append(
                AttachmentIndex(
                    offset=offset,
                    length=length,
                    log_time=rec.log_time,
                    create_time=rec.create_time,
                    data_size=len(rec.data),
                    name=rec.name,
                    media_type=rec.media_type,
                )
            )
        else:  # a chunk
            s, e = rec.message_start_time, rec.message_end_time
            start = s if start is None else min(start, s)
            end = e if end is None else max(end, e)
            chunk_idx.append(
                ChunkIndex(
                    message_start_time=s,
                    message_end_time=e,
                    chunk_start_offset=offset,
                    chunk_length=length,
                    message_index_offsets={},
                    message_index_length=0,
                    compression=rec.compression,
                    compressed_size=len(rec.data),
                    uncompressed_size=rec.uncompressed_size,
                )
            )
    counts.update({1: 41, 2: 3})  # what was counted (count(), add_message)
    out.write(_ref(DataEnd(data_section_crc=0)))
    summary_start = out.count
    stats = Statistics(
        message_count=44,
        schema_count=len(schemas),
        channel_count=len(channels),
        attachment_count=len(att_idx),
        metadata_count=len(meta_idx),
        chunk_count=len(chunk_idx),
        message_start_time=start,
        message_end_time=end,
        channel_message_counts=counts,
    )
    b = RecordBuilder()
    offsets = []
    for opcode, group in (
        (Opcode.SCHEMA, schemas),
        (Opcode.CHANNEL, channels),
        (Opcode.STATISTICS, [stats]),
        (Opcode.CHUNK_INDEX, chunk_idx),
        (Opcode.ATTACHMENT_INDEX, att_idx),
        (Opcode.METADATA_INDEX, meta_idx),
    ):
        at = b.count
        for rec in group:
            rec.write(b)
        offsets.append(SummaryOffset(opcode, summary_start + at, b.count - at))
    offset_start = summary_start + b.count
    for so in offsets:
        so.write(b)
    summary = b.end()
    crc = zlib.crc32(summary)
    crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), crc)
    out.write(summary)
    out.write(_ref(Footer(summary_start, offset_start, crc)))
    out.write(MCAP_MAGIC)
    assert out.end() == data


def test_the_write_path_imports_no_mcap_package() -> None:
    """Writing needs nothing of the ``mcap`` package (its records cost start-up)."""
    import subprocess
    import sys

    code = (
        "import io, sys\n"
        "from mbmon.io.mcap.writer import McapFileWriter\n"
        "w = McapFileWriter(io.BytesIO())\n"
        "w.start('x'); w.register_schema('s', 'json', b'{}'); w.register_channel('/t', 'json', 1)\n"
        "w.add_metadata('m', {'a': 'b'}); w.add_attachment(0, 1, 'n', 't', b'd')\n"
        "w.add_message(1, 5, b'{}'); w.finish()\n"
        "print(sorted(m for m in sys.modules if m == 'mcap' or m.startswith('mcap.')))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"
    assert writer_mod.OP_CHUNK == Opcode.CHUNK and writer_mod.OP_FOOTER == Opcode.FOOTER
