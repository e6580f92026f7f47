"""The MCAP sink (``-w FILE.mcap``): the recording Foxglove opens and ``mbmon replay`` reads.

A thin listener: what the log holds (topics, schemas, messages, metadata) is
:mod:`mbmon.io.mcap.layout`'s, how it is stored (chunks, compression, the
writer thread, crash safety, signals) :mod:`mbmon.io.mcap.writer`'s; this
module wires one to the other for a run.

- :meth:`McapSink.on_chunk` and :meth:`McapSink.on_record` only queue what they
  are given (a frame record with its ``read --json`` line, made in the calling
  thread); queued items become messages in batches (at most ``_BATCH`` items,
  or at the half-second flush);
- :meth:`McapSink.close` always finishes the file (summary, index, footer); the
  CLI turns SIGINT/SIGTERM into exceptions so ``close()`` runs, and after an
  interruption it can say where the log is (:attr:`McapSink.path`) and how
  much it holds (:attr:`McapSink.messages_written`);
- a write error (disk full) in the writer thread is raised as ``SinkError``
  by a later ``on_record`` (the next batch) or by ``close()``;
- the compiled core (``read -w x.mcap`` on :mod:`mbmon.core`) makes the message
  records itself, byte for byte those :meth:`LogLayout.convert` makes, and hands
  them over in blocks (:meth:`McapSink.put_packed`, about 1 MiB each) with the
  log's counters as of the block's end; the file around them (header, schemas,
  channels, metadata, chunks, summary) is this sink's either way.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mbmon import __version__
from mbmon.format import View
from mbmon.io.mcap.layout import (
    METADATA_NAME,
    PROFILE_MEDIA_TYPE,
    RECORD_TOPICS,
    SOURCE_EVENTS,
    TOPIC_COMMANDS,
    TOPIC_EVENTS,
    TOPIC_FRAMES,
    TOPIC_MONITOR,
    TOPIC_RAW,
    TOPIC_SCHEMAS,
    TOPIC_STATE,
    LogLayout,
    Totals,
    channel_schema,
    log_level,
    metadata,
    profile_attachment_name,
    schema_text,
    topics,
)
from mbmon.io.mcap.writer import CHUNK_SIZE, FLUSH_EVERY, ChunkedLog, McapFileWriter, WriteError
from mbmon.model import Chunk, Record
from mbmon.sinks.base import SinkBase, SinkContext, SinkError

__all__ = [
    "METADATA_NAME",
    "RECORD_TOPICS",
    "SOURCE_EVENTS",
    "TOPIC_COMMANDS",
    "TOPIC_EVENTS",
    "TOPIC_FRAMES",
    "TOPIC_MONITOR",
    "TOPIC_RAW",
    "TOPIC_SCHEMAS",
    "TOPIC_STATE",
    "McapSink",
    "log_level",
    "schema_text",
]

_BATCH = 128  # records (and raw chunks) moved into the open chunk at once, at most


@dataclass(frozen=True, slots=True)
class PackedMessages:
    """Message records the compiled core made (packed heads and data, in log order),
    their first and last log time, and the log's counters as of the last of them."""

    data: bytes
    first: int
    last: int
    totals: Totals


def _packed(items: list[Any]) -> tuple[list[bytes], int, int, Totals]:
    """The converter's form of :class:`PackedMessages` blocks: their records as they are."""
    first, last = items[0].first, items[0].last
    for item in items:
        if type(item) is not PackedMessages:  # a sink the core feeds takes nothing else
            raise TypeError(f"a record or chunk among the core's message blocks: {item!r}")
        first, last = min(first, item.first), max(last, item.last)
    return [item.data for item in items], first, last, items[-1].totals


def _is_chunk(item: Any) -> bool:
    """A captured chunk waits in the queue for the item after it (log format 4: its
    message is left out when that item is the frame it holds, ``chunk_marker``), so
    where a batch is cut never changes the log; :meth:`McapSink.close` writes it."""
    return type(item) is Chunk


class McapSink(SinkBase):
    """Write records and raw chunks to an MCAP file (see the module docstring)."""

    def __init__(
        self,
        path: str | Path,
        ctx: SinkContext,
        *,
        flush_every: float = FLUSH_EVERY,
        chunk_size: int = CHUNK_SIZE,
    ) -> None:
        self.path = Path(path)
        self.ctx = ctx
        self.view: View = ctx.view
        self._channels: dict[str, int] = {}
        self._layout: LogLayout | None = None
        self._batch = max(1, min(_BATCH, chunk_size >> 12))
        self._closed = False
        self._log = ChunkedLog(
            self.path,
            self._convert,
            self._start,
            chunk_size=chunk_size,
            flush_every=flush_every,
            hold=_is_chunk,
        )
        self._pending = self._log.pending
        assert self._layout is not None
        self._waiting_item: Callable[[Record], tuple[Record, bytes | dict[str, Any]]] = (
            self._layout.waiting_item
        )

    def _start(self, w: McapFileWriter) -> None:
        """Header, schemas, channels, metadata and profile attachments, on disk at once."""
        ctx = self.ctx
        w.start(library=f"mbmon {__version__}")
        with_profiles = bool(ctx.profiles or ctx.profile_specs)
        for topic in topics(with_profiles):
            name, schema_encoding, data, encoding = channel_schema(topic)
            schema_id = w.register_schema(name, schema_encoding, data)
            self._channels[topic] = w.register_channel(topic, encoding, schema_id)
        self._layout = LogLayout(ctx.view, ctx.source, self._channels)
        now_ns = time.time_ns()
        w.add_metadata(
            METADATA_NAME,
            metadata(
                version=__version__,
                command_line=ctx.command_line,
                source=ctx.source,
                profiles=ctx.profiles,
                profile_specs=ctx.profile_specs,
                timeout=ctx.timeout,
                baud=ctx.baud,
                view=ctx.view,
                started_ns=now_ns,
            ),
        )
        for name, text in ctx.profiles:
            w.add_attachment(
                create_time=0,
                log_time=now_ns,
                name=profile_attachment_name(name),
                media_type=PROFILE_MEDIA_TYPE,
                data=text.encode("utf-8"),
            )

    def _convert(self, items: list[Any], totals: Any) -> tuple[list[bytes], int, int, Any]:
        assert self._layout is not None
        if type(items[0]) is PackedMessages:
            return _packed(items)
        return self._layout.convert(items, totals)

    @property
    def layout(self) -> LogLayout:
        """What this log's messages hold (topics, channels, per-stream pieces)."""
        assert self._layout is not None
        return self._layout

    def write_here(self) -> None:
        """Compress and write chunks in the caller's thread from now on (the compiled
        core holds the GIL between its blocks: see ``ChunkedLog.write_here``)."""
        self._log.write_here()

    def put_packed(self, data: bytes, first: int, last: int, totals: Totals) -> None:
        """Message records made elsewhere (the compiled core), byte for byte what
        :meth:`LogLayout.convert` makes of the same records and chunks, with ``first``
        and ``last`` their log-time range and ``totals`` the log's counters once they
        are in (a copy the caller no longer changes). They enter the open chunk as one
        piece, counters with them, as a batch of :meth:`on_record` does."""
        if data:
            self._pending.append(PackedMessages(data, first, last, totals))
            self._move()

    # ------------------------------------------------------------------ listener hooks

    def on_chunk(self, chunk: Chunk) -> None:
        """One captured chunk on /modbus/raw (made into its message with the next batch
        after the item that follows it: format 4 leaves out the message of a chunk that
        is the next frame's ADU)."""
        self._pending.append(chunk)

    def on_record(self, record: Record) -> None:
        """Write the messages of one record on their topics.

        What depends on the view is made here, in the calling thread (the
        ``read --json`` line of a frame record, the object of another); the
        messages are made from it in batches. Events, noise and commands are
        few and written out at once.
        """
        pending = self._pending
        pending.append(self._waiting_item(record))
        if record.frame is None or len(pending) >= self._batch:
            self._move()

    def on_records(self, records: list[Record]) -> None:
        """A batch of records, as :meth:`on_record` takes them one by one (the hub calls
        this in the order listeners were added: ``read`` adds its logs before the
        console, so a record printed on stdout is in the log's waiting list first)."""
        pending = self._pending
        waiting_item = self._waiting_item
        due = False
        for record in records:
            pending.append(waiting_item(record))
            if record.frame is None:
                due = True
        if due or len(pending) >= self._batch:
            self._move()

    def _move(self) -> None:
        try:
            self._log.move()
        except WriteError as exc:
            raise SinkError(str(exc)) from exc.__cause__

    @property
    def messages_written(self) -> int:
        """Messages in the log so far (in its chunks, or on their way there)."""
        if self._closed:
            return self._log.writer.message_count
        if self._layout is None:
            return 0
        totals = self._log.state or self._layout.new_totals()
        return sum(self._layout.channel_counts(totals).values())

    def close(self) -> None:
        """Write what is left and finish the file (summary, index, footer).

        SIGINT/SIGTERM are held back meanwhile: a second Ctrl-C cannot leave
        the file unfinished. The Statistics record counts what the chunks hold.
        """
        if self._closed:
            return
        self._closed = True
        layout = self._layout
        assert layout is not None

        def finish(w: McapFileWriter) -> None:
            totals = w.state or layout.new_totals()
            final = layout.final_stats(totals)
            if final is not None:
                topic, log_time, data = final
                w.append(self._channels[topic], log_time, data)
            for channel_id, count in layout.channel_counts(totals).items():
                w.count(channel_id, count)

        try:
            self._log.close(finish)
        except WriteError as exc:
            raise SinkError(str(exc)) from exc.__cause__
