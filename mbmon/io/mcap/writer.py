"""Writing MCAP files: records, chunks, compression, the writer thread, crash safety.

This module knows MCAP, not mbmon's topics (those are :mod:`mbmon.io.mcap.layout`'s):

- :class:`McapFileWriter` lays out a file the way ``mcap.writer.Writer`` does,
  built for many small messages: message records are packed by the caller
  (:data:`MESSAGE_HEAD`) and enter the open chunk in batches
  (:meth:`McapFileWriter.take_from`); schemas and channels are written before
  the first chunk, so that every chunk of a file cut short reads on its own;
- :class:`ChunkedLog` runs one on a file with a writer thread: chunks are zstd
  compressed (lz4, then none, when those are missing); the open chunk is
  closed every ``flush_every`` seconds of wall time (by :meth:`ChunkedLog.move`
  while messages flow, by the writer thread when they stop) and the thread
  compresses and writes it, so a killed process loses at most the last second;
  zstd, joining the chunk and file writes release the GIL, so that work
  overlaps with decoding. A write error (disk full) in the thread is raised
  by the next :meth:`ChunkedLog.move` or by :meth:`ChunkedLog.close`.

Signals (SIGINT/SIGTERM turned into exceptions by the CLI) may interrupt the
calling thread between any two bytecodes. Each hand-over is therefore one run
of statements with no call in between (where CPython runs signal handlers):
waiting items become message records in the open chunk together with the
converter's state (its counters) in :meth:`McapFileWriter.take_from`, and a
closed chunk joins the list the writer thread takes from in
:meth:`McapFileWriter.close_chunk_into`. So an item is in the file, or still
waiting, never both or neither, and the counters (the Statistics record) count
exactly what the chunks hold. The writer thread blocks those signals, and
:meth:`ChunkedLog.close` defers them until the file is finished.
"""

from __future__ import annotations

import signal
import struct
import sys
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

#: the C module under ``signal`` (CPython's ``signal`` imports it), else ``signal`` itself
_signal_c: Any = sys.modules.get("_signal", signal)

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: the head of a message record: opcode, length, channel, sequence, log time, publish time
MESSAGE_HEAD = struct.Struct("<BQHIQQ")
OP_MESSAGE = 0x05
_CHUNK_HEAD = struct.Struct("<BQQQQII")  # opcode, length, start, end, size, crc, name length
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
#: a chunk index record up to its compression's name: opcode, length, start, end, the
#: chunk's offset and length, an empty message index map, its length (0), the name's length
_CHUNK_INDEX_HEAD = struct.Struct("<BQQQQQIQI")
_SIZES = struct.Struct("<QQ")  # a chunk index's compressed and uncompressed sizes
# MCAP opcodes (the spec's; the same as ``mcap.opcode.Opcode``)
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL = 0x01, 0x02, 0x03, 0x04
OP_CHUNK, OP_CHUNK_INDEX, OP_ATTACHMENT, OP_ATTACHMENT_INDEX = 0x06, 0x08, 0x09, 0x0A
OP_STATISTICS, OP_METADATA, OP_METADATA_INDEX = 0x0B, 0x0C, 0x0D
OP_SUMMARY_OFFSET, OP_DATA_END = 0x0E, 0x0F
#: the largest log time a message record holds (ns since the epoch, about the year 2554)
MAX_LOG_TIME = (1 << 64) - 1
#: chunk compression level. Compression is most of a log's cost once records are made
#: fast (the compiled core: over half of `read -q -w x.mcap`'s CPU at level 2); a fast
#: (negative) level takes about a third less CPU than level 2 for files about a third
#: larger (docs/performance.md, "The log's message volume")
ZSTD_LEVEL = -3
FLUSH_EVERY = 0.5  # seconds of wall time between chunk flushes (at most 1 s is promised)
CHUNK_SIZE = 1 << 20
_READY_MAX = 4  # closed chunks waiting for the writer thread before the caller waits
_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: the C module's ``signal()``: ``signal.signal`` converts its arguments and result to
#: and from enums (an exception raised and caught for a Python handler), about 4 us a
#: call, four calls a chunk written
_set_handler: Callable[[int, Any], Any] = getattr(_signal_c, "signal", signal.signal)
_SIGNAL_NUMBERS = tuple(int(sig) for sig in _SIGNALS)

#: makes waiting items into message records:
#: ``convert(items, state) -> (records, first log time, last log time, new state)``
Converter = Callable[[list[Any], Any], tuple[list[bytes], int, int, Any]]


class PendingChunk:
    """A closed chunk's uncompressed records (in pieces, joined when written) and time range,
    waiting to be written. (A plain class: a dataclass costs every ``-w`` run about
    0.5 ms of start-up to make.)"""

    __slots__ = ("data", "end", "start")

    def __init__(self, data: list[bytes], start: int, end: int) -> None:
        self.data = data
        self.start = start
        self.end = end

    def __repr__(self) -> str:
        return f"PendingChunk({len(self.data)} pieces, {self.start}..{self.end})"


def _pick_compression() -> tuple[str, Callable[[bytes], bytes] | None]:
    """The best chunk compression available: zstd, then lz4, then none."""
    try:
        import zstandard

        # the frame's own checksum (XXH64, checked on every decompression) stands for the
        # chunk's CRC-32, which a zstd chunk leaves 0 (MCAP: not computed): the CRC of
        # the uncompressed chunks took about 0.3 s of CPU per million ADUs; damage is
        # still found, as a chunk that does not decompress
        return "zstd", zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_checksum=True).compress
    except ImportError:
        pass
    try:
        import lz4.frame  # type: ignore[import-not-found, import-untyped, unused-ignore]

        return "lz4", lz4.frame.compress
    except ImportError:
        return "", None


def _record(opcode: int, *body: bytes) -> bytes:
    """One MCAP record: its opcode, its length and its body (the pieces joined)."""
    data = b"".join(body)
    return _RECORD_HEAD.pack(opcode, len(data)) + data


def _text(value: str) -> bytes:
    """An MCAP string: its UTF-8 length (u32), then its bytes."""
    data = value.encode()
    return _U32.pack(len(data)) + data


def _texts(pairs: dict[str, str]) -> bytes:
    """An MCAP map of strings to strings: its length in bytes (u32), then the pairs."""
    data = b"".join(_text(k) + _text(v) for k, v in pairs.items())
    return _U32.pack(len(data)) + data


def _counts(counts: dict[int, int]) -> bytes:
    """An MCAP map of channel ids (u16) to counts (u64)."""
    data = b"".join(struct.pack("<HQ", k, v) for k, v in counts.items())
    return _U32.pack(len(data)) + data


class McapFileWriter:
    """An MCAP writer for many small messages, byte for byte the ``mcap`` package's layout.

    ``mcap.writer.Writer`` spends about 20 us of Python per message (a record
    object, a message index entry, eight small writes); here a message record is
    one ``struct.pack`` of its head and its data, handed over in batches
    (:meth:`take_from`) into the open chunk, a list of pieces joined once when
    the chunk is written, and every other record (header, schemas, channels,
    chunks, metadata, attachments, statistics, indexes, footer) is packed here as
    the ``mcap`` package's records write themselves, laid out as
    ``Writer.finish`` does (the package is not imported to write: its record
    classes cost a run about 6 ms of start-up, and a chunk's index record through
    them about 20 us). Schemas and channels are written once, before the
    first chunk and outside it, so that every chunk of a file cut short can be
    read on its own. No message index records are written (readers scan a
    chunk without them); chunk, metadata and attachment indexes are.
    """

    def __init__(self, stream: IO[bytes], *, chunk_size: int = 1 << 20) -> None:
        self._f = stream
        #: where the next record starts (the stream's position, counted here: no
        #: ``tell()``, a system call, per chunk)
        self._pos = stream.tell()
        self.compression, self._compress = _pick_compression()
        self.chunk_size = chunk_size
        #: the open chunk: its message records in pieces, joined once when it is written
        #: (growing one buffer would copy every byte again at each reallocation)
        self._parts: list[bytes] = []
        self._size = 0  # bytes in _parts
        self._chunk_start = 0
        self._chunk_end = 0
        self._schemas: list[bytes] = []  # Schema records, serialized
        self._channels: list[bytes] = []  # Channel records, serialized
        self._counts: dict[int, int] = {}
        self._start_time = 0
        self._end_time = 0
        self._chunk_indexes: list[bytes] = []  # ChunkIndex records, serialized
        self._metadata_indexes: list[bytes] = []  # MetadataIndex records, serialized
        self._attachment_indexes: list[bytes] = []  # AttachmentIndex records, serialized
        #: the converter's state as of the last messages that entered the chunks
        #: (see :meth:`take_from`); ``None`` until then
        self.state: Any = None

    def _put(self, data: bytes) -> None:
        """Write ``data`` at the end of the file (and count it in :attr:`_pos`)."""
        self._f.write(data)
        self._pos += len(data)

    def start(self, library: str) -> None:
        self._put(MCAP_MAGIC + _record(OP_HEADER, _text(""), _text(library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = len(self._schemas) + 1
        record = _record(
            OP_SCHEMA, struct.pack("<H", schema_id), _text(name), _text(encoding),
            _U32.pack(len(data)), data,
        )  # fmt: skip
        self._schemas.append(record)
        self._put(record)
        return schema_id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        channel_id = len(self._channels) + 1
        record = _record(
            OP_CHANNEL, struct.pack("<HH", channel_id, schema_id), _text(topic),
            _text(message_encoding), _texts({}),
        )  # fmt: skip
        self._channels.append(record)
        self._counts[channel_id] = 0
        self._put(record)
        return channel_id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self._pos
        record = _record(OP_METADATA, _text(name), _texts(data))
        self._put(record)
        self._metadata_indexes.append(
            _record(OP_METADATA_INDEX, _SIZES.pack(offset, len(record)), _text(name))
        )

    def add_attachment(
        self, create_time: int, log_time: int, name: str, media_type: str, data: bytes
    ) -> None:
        offset = self._pos
        body = b"".join(
            (_SIZES.pack(log_time, create_time), _text(name), _text(media_type),
             _U64.pack(len(data)), data)
        )  # fmt: skip
        record = _record(OP_ATTACHMENT, body, _U32.pack(zlib.crc32(body)))
        self._put(record)
        self._attachment_indexes.append(
            _record(
                OP_ATTACHMENT_INDEX,
                _SIZES.pack(offset, len(record)),
                _SIZES.pack(log_time, create_time),
                _U64.pack(len(data)),
                _text(name),
                _text(media_type),
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
        record = MESSAGE_HEAD.pack(0x05, 22 + len(data), channel_id, 0, log_time, log_time) + data
        self._parts.append(record)
        self._counts[channel_id] += 1
        self._size += len(record)
        return self._size

    @property
    def message_count(self) -> int:
        """Messages counted so far (all of them once :meth:`finish` ran)."""
        return sum(self._counts.values())

    def count(self, channel_id: int, messages: int) -> None:
        """Count ``messages`` more on a channel in the statistics: messages whose heads
        the caller packed itself (with ``MESSAGE_HEAD``) and handed to :meth:`take_from`."""
        self._counts[channel_id] += messages

    def take_from(
        self, pending: list[Any], convert: Converter, hold: Callable[[Any], bool] | None = None
    ) -> int:
        """Move what waits in ``pending`` to the end of the open chunk as message records
        (``convert(items, self.state)`` makes them) and remove it from the list; the
        converter's new state becomes :attr:`state` with them. Return the open chunk's
        size (the caller closes it). A last item that ``hold`` holds stays waiting (a
        chunk whose message depends on the item after it: log format 4).

        Another thread may append to ``pending`` meanwhile: only the items there at
        the start are moved. The chunk gains their records by one in-place list
        concatenation, the list loses them by one slice deletion and the state is
        replaced, with no call in between (where CPython runs signal handlers), so a
        handler that raises leaves every item either in the chunk (and counted) or
        still waiting (and not), never both or neither.
        """
        n = len(pending)
        if n and hold is not None and hold(pending[n - 1]):
            n -= 1
        if not n:
            return self._size
        records, start, end, state = convert(pending[:n], self.state)
        size = self._size + sum(map(len, records))
        if not records:
            start, end = self._chunk_start, self._chunk_end
        elif self._parts:
            start = min(start, self._chunk_start)
            end = max(end, self._chunk_end)
        parts = self._parts
        # one run without calls: the records, the waiting list, the state, the size
        parts += records
        del pending[:n]
        self.state = state
        self._size = size
        self._chunk_start, self._chunk_end = start, end
        return size

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

    def close_chunk_into(self, ready: list[PendingChunk]) -> None:
        """Detach the open chunk (if any) to the end of ``ready``, in one run of statements
        without calls: a signal handler that raises finds it in the chunk or in ``ready``."""
        parts = self._parts
        if not parts:
            return
        chunk = PendingChunk(parts, self._chunk_start, self._chunk_end)
        self._parts = []
        self._size = 0
        ready += (chunk,)

    def write_chunk(self, pending: PendingChunk) -> None:
        """Compress and write a detached chunk, and index it (chunks in order).

        A chunk of one piece (a block of the compiled core) is compressed where it is:
        ``b"".join`` of one bytes object returns that object."""
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
            0 if self.compression == "zstd" else zlib.crc32(data),  # zstd: its checksum
            len(name),
        )
        offset = self._pos
        self._put(head + name + _U64.pack(len(packed)))
        self._put(packed)
        # kept as its record's bytes until the summary: one a chunk for the whole run,
        # about 100 bytes instead of a ChunkIndex object's 320 (a long proxy -w run)
        self._chunk_indexes.append(
            _CHUNK_INDEX_HEAD.pack(
                OP_CHUNK_INDEX,
                8 + 8 + 8 + 8 + 4 + 8 + 4 + len(name) + 8 + 8,
                pending.start,
                pending.end,
                offset,
                len(head) + len(name) + 8 + len(packed),
                0,  # no message indexes
                0,
                len(name),
            )
            + name
            + _SIZES.pack(len(packed), len(data))
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
        self.close_chunk()
        self._put(_record(OP_DATA_END, _U32.pack(0)))
        summary_start = self._pos
        stats = _record(
            OP_STATISTICS,
            struct.pack(
                "<QHIIIIQQ",
                sum(self._counts.values()),
                len(self._schemas),
                len(self._channels),
                len(self._attachment_indexes),
                len(self._metadata_indexes),
                len(self._chunk_indexes),
                self._start_time,
                self._end_time,
            ),
            _counts(self._counts),
        )
        groups: tuple[tuple[int, list[bytes]], ...] = (
            (OP_SCHEMA, self._schemas),
            (OP_CHANNEL, self._channels),
            (OP_STATISTICS, [stats]),
            (OP_CHUNK_INDEX, self._chunk_indexes),
            (OP_ATTACHMENT_INDEX, self._attachment_indexes),
            (OP_METADATA_INDEX, self._metadata_indexes),
        )
        parts: list[bytes] = []
        offsets: list[bytes] = []
        size = 0
        for opcode, records in groups:
            length = sum(map(len, records))
            parts += records
            group = struct.pack("<BQQ", opcode, summary_start + size, length)
            offsets.append(_record(OP_SUMMARY_OFFSET, group))
            size += length
        offset_start = summary_start + size
        summary = b"".join(parts + offsets)
        footer = _RECORD_HEAD.pack(OP_FOOTER, 20) + _SIZES.pack(summary_start, offset_start)
        crc = zlib.crc32(footer, zlib.crc32(summary))
        self._put(summary + footer + _U32.pack(crc) + MCAP_MAGIC)
        self._f.flush()


class WriteError(Exception):
    """Writing the file failed (disk full, I/O error); the message names the file."""


class ChunkedLog:
    """An MCAP file written by a writer thread; messages reach it in batches.

    ``start(writer)`` writes what precedes the data (header, schemas, channels,
    metadata, attachments) while the file is opened. Then callers append
    items to :attr:`pending` (one atomic list append, no lock) and call
    :meth:`move`, which makes them into message records with ``convert`` (see
    :meth:`McapFileWriter.take_from`) and closes the chunk when it is full or
    due. :meth:`close` moves what is left, lets ``finish(writer)`` add its last
    messages and per-channel counts, and finishes the file (summary, index,
    footer), with SIGINT/SIGTERM deferred meanwhile.
    """

    def __init__(
        self,
        path: str | Path,
        convert: Converter,
        start: Callable[[McapFileWriter], None],
        *,
        chunk_size: int = CHUNK_SIZE,
        flush_every: float = FLUSH_EVERY,
        hold: Callable[[Any], bool] | None = None,
    ) -> None:
        self.path = Path(path)
        #: a last waiting item this holds stays waiting until another follows it, or the
        #: close (:meth:`McapFileWriter.take_from`): the batch's cut never decides for it
        self.hold = hold
        self.chunk_size = chunk_size
        self.flush_every = flush_every
        self._convert = convert
        self._file: IO[bytes] = open(self.path, "wb")
        self.writer = McapFileWriter(self._file, chunk_size=chunk_size)
        try:
            start(self.writer)
            self._file.flush()
        except BaseException:
            self._file.close()
            raise
        #: items waiting to become messages, in order (appended without the lock)
        self.pending: list[Any] = []
        self._ready: list[PendingChunk] = []  # closed chunks, in order, for the thread
        self._lock = threading.Lock()
        self._wake = threading.Event()  # a chunk is ready, or close() was called
        self._drained = threading.Event()  # the thread wrote a chunk
        self._stopping = False
        self._closed = False
        self._error: BaseException | None = None
        self._error_raised = False
        self._last_flush = time.monotonic()
        self._worker: threading.Thread | None = threading.Thread(
            target=self._work, name="mbmon-mcap-writer", daemon=True
        )
        self._worker.start()

    def write_here(self) -> None:
        """From now on the caller's thread compresses and writes each chunk as it is
        closed (in :meth:`move` and :meth:`close`); the writer thread ends.

        For a caller that holds the GIL for long stretches of compiled code (the
        compiled core): a writer thread would wait for it at every step between
        its GIL-free calls, and the two would take turns rather than overlap.
        Each chunk is written with SIGINT/SIGTERM deferred, so an interruption
        never leaves half a chunk in the file. Idempotent.
        """
        worker = self._worker
        if worker is None:
            return
        with self._lock:
            self._stopping = True
        self._wake.set()
        worker.join()  # it writes what was ready, then ends
        self._worker = None
        self._stopping = False

    def _write_ready(self) -> None:
        """Without a writer thread: write the closed chunks now, signals deferred."""
        ready = self._ready
        with _signals_deferred():
            while ready and self._error is None:
                chunk = ready.pop(0)
                try:
                    self.writer.write_chunk(chunk)
                    self._file.flush()
                except Exception as exc:  # disk full, I/O error: raised below
                    self._error = exc
            ready.clear()
        if self._error is not None:
            self._raise_error()

    @property
    def state(self) -> Any:
        """The converter's state as of the messages in the chunks (committed with them)."""
        return self.writer.state

    def move(self) -> None:
        """Make the waiting items into messages of the open chunk; close it when full or due.

        Raises :class:`WriteError` once after the writer thread failed.
        """
        if self._error is not None:
            self._raise_error()
        ready = self._ready
        with self._lock:
            size = self.writer.take_from(self.pending, self._convert, self.hold)
            if size > self.chunk_size or time.monotonic() - self._last_flush >= self.flush_every:
                self.writer.close_chunk_into(ready)
                self._last_flush = time.monotonic()
                self._wake.set()
        if self._worker is None:
            if ready:
                self._write_ready()
            return
        while len(ready) > _READY_MAX and self._error is None and self._worker.is_alive():
            self._drained.wait(0.05)  # back pressure: the thread is behind
            self._drained.clear()

    def close(self, finish: Callable[[McapFileWriter], None] | None = None) -> None:
        """Write what is left and finish the file (summary, index, footer); idempotent.

        ``finish(writer)`` runs after the last items became messages and before the
        last chunk is closed (the place for closing messages and for
        :meth:`McapFileWriter.count`). SIGINT/SIGTERM are deferred meanwhile (to
        the moment the file is complete), so a second Ctrl-C cannot leave it
        unfinished. Items that fail to convert are dropped and reported (as
        :class:`WriteError`) after the file is finished.
        """
        if self._closed:
            return
        self._closed = True
        failure: BaseException | None = None
        with _signals_deferred():
            try:
                with self._lock:
                    try:
                        self.writer.take_from(self.pending, self._convert)
                    except Exception as exc:  # a bug in making messages: keep the rest
                        failure = exc
                        self.pending.clear()
                    if finish is not None:
                        finish(self.writer)
                    self.writer.close_chunk_into(self._ready)
                    self._stopping = True
                self._wake.set()
                if self._worker is not None:
                    self._worker.join()
                elif self._error is None:
                    self._write_ready_at_close()
                if self._error is None:
                    self.writer.finish()
            finally:
                self._file.close()
        self._raise_error()
        if failure is not None:
            raise WriteError(f"{self.path}: messages lost: {failure}") from failure

    def _write_ready_at_close(self) -> None:
        """:meth:`close` without a writer thread: the last chunks (signals are deferred
        already); a failure is kept for :meth:`close` to raise once the file is closed."""
        for chunk in self._ready:
            try:
                self.writer.write_chunk(chunk)
            except Exception as exc:  # disk full, I/O error
                self._error = exc
                break
        self._ready.clear()

    def _raise_error(self) -> None:
        if self._error is not None and not self._error_raised:
            self._error_raised = True
            error = self._error
            what = getattr(error, "strerror", None) or error
            raise WriteError(f"{self.path}: cannot write: {what}") from error

    def _work(self) -> None:
        """Writer thread: compress and write chunks (zstd and the file release the GIL, so
        this overlaps with decoding), and close the open chunk when items stop coming."""
        _block_signals()
        tick = max(0.05, self.flush_every / 4)
        ready = self._ready
        while True:
            self._wake.clear()
            chunk: PendingChunk | None = None
            with self._lock:
                if ready:
                    chunk = ready.pop(0)
                elif self._stopping:
                    return
                elif time.monotonic() - self._last_flush >= self.flush_every:
                    try:
                        self.writer.take_from(self.pending, self._convert, self.hold)
                    except Exception as exc:  # reported by the next move() or close()
                        if self._error is None:
                            self._error = exc
                    self.writer.close_chunk_into(ready)
                    self._last_flush = time.monotonic()
                    continue
            if chunk is None:
                self._wake.wait(tick)
                continue
            if self._error is not None:
                self._drained.set()
                continue  # after a write error: drain, so the caller never blocks
            try:
                self.writer.write_chunk(chunk)
                self._file.flush()
            except Exception as exc:  # disk full, I/O error: reported on the next move
                self._error = exc
            self._drained.set()


def _block_signals() -> None:
    """Keep SIGINT/SIGTERM away from this (non-main) thread: they go to the main thread."""
    try:
        signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    except (AttributeError, OSError, ValueError):  # platforms without pthread_sigmask
        pass


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT/SIGTERM back for the duration; then act on the first one that came.

    Python handlers run in the main thread whichever thread the signal reached,
    so the handlers themselves are swapped for ones that only take note (main
    thread only; elsewhere handlers never run anyway).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    old: dict[int, Any] = {}
    try:
        for sig in _SIGNAL_NUMBERS:
            old[sig] = _set_handler(sig, lambda signum, frame: caught.append(signum))
    except (OSError, ValueError):  # not allowed here: go without
        pass
    try:
        yield
    finally:
        for sig, handler in old.items():
            _set_handler(sig, handler if handler is not None else signal.SIG_DFL)
        if caught:
            signal.raise_signal(caught[0])
