"""JSON Lines sink (``-w FILE.jsonl``): exactly the lines ``mbmon read --json`` prints.

Uses the one JSON line encoding of ``read --json`` (:func:`mbmon.format.json_line`),
as do ``replay --json`` and ``export .jsonl``, so that all four agree byte for byte.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from mbmon.format import json_line, record_to_json
from mbmon.model import Record
from mbmon.sinks.base import SinkBase, SinkContext

#: the encoder of ``read --json`` lines (mbmon.format.json_line: compact, non-ASCII kept)
dumps_line = json_line

FLUSH_EVERY = 1.0  # seconds of wall time between flushes of text sinks


class TextFileSink(SinkBase):
    """Base of the line-oriented sinks: a UTF-8 text file flushed at least once a second."""

    def __init__(self, path: str | Path, ctx: SinkContext, *, newline: str | None = "\n") -> None:
        self.path = Path(path)
        self.ctx = ctx
        self.view = ctx.view
        self._f = open(self.path, "w", encoding="utf-8", newline=newline)
        self._last_flush = time.monotonic()
        self._closed = False

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
    """One ``read --json`` object per line for every record."""

    def write(self, record: Record) -> None:
        self.write_obj(record_to_json(record, self.view))

    def write_obj(self, obj: Mapping[str, Any]) -> None:
        """Write one already-made ``read --json`` object (used by ``mbmon export``)."""
        self._f.write(dumps_line(obj) + "\n")
        self._tick()
