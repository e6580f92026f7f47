"""JSON Lines sink (``-w FILE.jsonl``): exactly the lines ``mbmon read --json`` prints.

Records go through the same fast encoder as ``read --json`` to stdout
(:func:`mbmon.jsonfmt.record_json_bytes`, UTF-8 bytes written to a binary file:
no text layer, no encode step); records read back from a log (``mbmon export``,
:class:`~mbmon.stored.StoredRecord`) give their stored object through the same
function, as ``replay --json`` prints it, so that all four agree byte for byte.

Also owns :class:`TextFileSink`, the base of the line-oriented sinks (file
opening, the flush that puts every line on disk within a second — on each
write once a second has passed, and on every hub tick, so a live input that
stalls never holds lines back —, and write errors that name the file:
``x.jsonl: No space left on device``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import IO, Any

from mbmon.format import json_line
from mbmon.jsonfmt import record_json_bytes
from mbmon.model import Record
from mbmon.sinks.base import SinkBase, SinkContext
from mbmon.stored import json_less

#: the encoder of ``read --json`` lines (mbmon.format.json_line: compact, non-ASCII kept)
dumps_line = json_line

FLUSH_EVERY = 1.0  # seconds of wall time between flushes of text sinks
BUFFER_SIZE = 1 << 18  # bytes buffered between writes to the OS (fewer system calls)


class TextFileSink(SinkBase):
    """Base of the line-oriented sinks: a UTF-8 text file flushed at least once a second."""

    def __init__(self, path: str | Path, ctx: SinkContext, *, newline: str | None = "\n") -> None:
        self.path = Path(path)
        self.ctx = ctx
        self.view = ctx.view
        self._f: IO[Any] = self._open(newline)
        self._last_flush = time.monotonic()
        self._closed = False

    def _named(self, exc: OSError) -> OSError:
        """``exc`` with this sink's file named: the hub and ``export`` report
        ``FILE: reason`` (a full disk: ``x.jsonl: No space left on device``)."""
        return OSError(exc.errno, exc.strerror or str(exc), exc.filename or str(self.path))

    def _open(self, newline: str | None) -> IO[Any]:
        """The output file: UTF-8 text, lines ended by ``newline``."""
        return open(self.path, "w", encoding="utf-8", newline=newline, buffering=BUFFER_SIZE)

    def _tick(self) -> None:
        """After a write: flush when the last flush is a second old."""
        if time.monotonic() - self._last_flush >= FLUSH_EVERY:
            self._flush()

    def _flush(self) -> None:
        """Everything written so far to the OS (where a SIGKILL no longer loses it)."""
        self._last_flush = time.monotonic()
        try:
            self._f.flush()
        except OSError as exc:
            raise self._named(exc) from exc

    def on_tick(self, now: float) -> None:
        """Time moves on (the hub ticks every quarter second on a live input, also while
        nothing arrives): what was written reaches the file now."""
        if not self._closed:
            self._flush()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._f.close()
            except OSError as exc:
                raise self._named(exc) from exc


class JsonlSink(TextFileSink):
    """One ``read --json`` line per record, written as UTF-8 bytes."""

    def _open(self, newline: str | None) -> IO[Any]:
        return open(self.path, "wb", buffering=BUFFER_SIZE)

    def on_record(self, record: Record) -> None:
        if record.frame is None and json_less(record):
            return  # a stored record cut by a crash: a line, no object to write
        try:
            self._f.write(record_json_bytes(record, self.view) + b"\n")
        except OSError as exc:
            raise self._named(exc) from exc
        now = time.monotonic()  # _tick, inlined: this runs once per record
        if now - self._last_flush >= FLUSH_EVERY:
            self._tick()
