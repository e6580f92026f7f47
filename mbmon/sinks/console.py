"""The console listener: records as monitor lines or JSON lines on stdout.

Lines are written in blocks of about :data:`BLOCK` records, one ``write`` per
block; with ``live`` (input that arrives as it happens: a pipe, a live
capture, the proxy) every batch is written and flushed at once, and
``on_tick`` flushes whatever waits, so no line waits for later input. JSON
lines are made in UTF-8 and go straight to the binary buffer under stdout when
that gives the same bytes (:func:`utf8_buffer`).
"""

from __future__ import annotations

import codecs
import os
from collections.abc import Callable
from typing import IO, Any

from mbmon.format import View, record_line
from mbmon.jsonfmt import record_json_bytes
from mbmon.model import Record

#: Console lines are written in blocks of this many records (with stdout
#: unbuffered, every line was a system call).
BLOCK = 512


class RawStdout:
    """The compiled core's way to the console: its bytes go to stdout's binary buffer;
    a reader that went away (``| head``) silences stdout once, as the hub does, and
    every later write or flush is dropped (:attr:`broken`)."""

    def __init__(self, buffer: IO[bytes]) -> None:
        self.buffer = buffer
        self.broken = False

    def write(self, data: bytes) -> None:
        if not self.broken:
            try:
                self.buffer.write(data)
            except BrokenPipeError:
                self._gone()

    def flush(self) -> None:
        if not self.broken:
            try:
                self.buffer.flush()
            except BrokenPipeError:
                self._gone()

    def _gone(self) -> None:
        from mbmon.hub import _quiet_stdout

        self.broken = True
        _quiet_stdout()


def utf8_buffer(out: IO[str]) -> IO[bytes] | None:
    """The binary buffer under the text stream ``out`` when writing UTF-8 bytes there
    is the same as writing their text to ``out`` (UTF-8 encoding, no newline
    translation), after flushing ``out``; else ``None``."""
    buffer: IO[bytes] | None = getattr(out, "buffer", None)
    encoding = getattr(out, "encoding", None)
    if buffer is None or not isinstance(encoding, str) or os.linesep != "\n":
        return None
    try:
        if codecs.lookup(encoding).name != "utf-8":
            return None
    except LookupError:
        return None
    out.flush()
    return buffer


class ConsoleListener:
    """Prints every record it is given, as text or JSON lines, to ``out``."""

    name = "stdout"

    def __init__(self, out: IO[str], view: View, *, as_json: bool = False, live: bool = False):
        self.view = view
        self.live = live
        buffer = utf8_buffer(out) if as_json else None
        self._encode: Callable[[Record, View], Any]
        self._newline: Any  # str, or bytes when the lines go to stdout's binary buffer
        self._target: IO[Any]
        if buffer is not None:
            self._encode, self._newline, self._target = record_json_bytes, b"\n", buffer
        elif as_json:
            self._encode = lambda record, view: record_json_bytes(record, view).decode()
            self._newline, self._target = "\n", out
        else:
            self._encode, self._newline, self._target = record_line, "\n", out
        self._lines: list[Any] = []

    def on_records(self, records: list[Record]) -> None:
        encode, view = self._encode, self.view
        lines = self._lines
        lines.extend([encode(record, view) for record in records])
        if self.live or len(lines) >= BLOCK:
            self._write()

    def on_tick(self, now: float) -> None:
        """Time moved on with nothing new: what waits goes out now (a live stream that
        fell idle shows its last lines within one listener tick)."""
        if self._lines:
            self._write()
            self._target.flush()

    def _write(self) -> None:
        """Write the waiting lines, each once: they leave the list before the write,
        so a Ctrl-C inside it (``KeyboardInterrupt``) cannot leave them to be written
        again by :meth:`close` (nor an empty line: the list once kept the
        terminator it had been given for the join)."""
        lines = self._lines
        if lines:
            self._lines = []
            lines.append(self._newline[:0])  # the last line's terminator, from the join
            self._target.write(self._newline.join(lines))
        if self.live:
            self._target.flush()

    def close(self) -> None:
        self._write()
        self._target.flush()
