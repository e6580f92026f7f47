"""JSON Lines sink (``-w FILE.jsonl``): exactly the lines ``mbmon read --json`` prints.

Records go through the same fast encoder as ``read --json`` to stdout
(:func:`mbmon.format.record_json_bytes`, UTF-8 bytes written to a binary file:
no text layer, no encode step); already-made objects (``mbmon export``) through
:func:`mbmon.format.json_line`, which gives the same bytes, as ``replay --json``
does, so that all four agree byte for byte.

Also owns :class:`TextFileSink`, the base of the line-oriented sinks (file
opening and the at-least-once-a-second flush).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from mbmon.format import json_line, record_json_bytes
from mbmon.model import Record
from mbmon.sinks.base import SinkBase, SinkContext

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

    def _open(self, newline: str | None) -> IO[Any]:
        """The output file: UTF-8 text, lines ended by ``newline``."""
        return open(self.path, "w", encoding="utf-8", newline=newline, buffering=BUFFER_SIZE)

    def _tick(self) -> None:
        now = time.monotonic()
        if now - self._last_flush >= FLUSH_EVERY:
            self._f.flush()
            self._last_flush = now

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._f.close()


class JsonlSink(TextFileSink):
    """One ``read --json`` line per record, written as UTF-8 bytes."""

    def _open(self, newline: str | None) -> IO[Any]:
        return open(self.path, "wb", buffering=BUFFER_SIZE)

    def on_record(self, record: Record) -> None:
        self._f.write(record_json_bytes(record, self.view) + b"\n")
        now = time.monotonic()  # _tick, inlined: this runs once per record
        if now - self._last_flush >= FLUSH_EVERY:
            self._f.flush()
            self._last_flush = now

    def write_obj(self, obj: Mapping[str, Any]) -> None:
        """Write one already-made ``read --json`` object (used by ``mbmon export``)."""
        self._f.write((dumps_line(obj) + "\n").encode("utf-8"))
        self._tick()
