"""Text sink (``-w FILE.txt``): the monitor lines exactly as the console prints them.

One line per record, as the robot's Modbus Monitor would export them: time,
label, function code + data in hex, then the notes.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from mbmon.format import record_line
from mbmon.model import Record
from mbmon.sinks.jsonl import TextFileSink


class TextSink(TextFileSink):
    """The console's monitor line for every record."""

    def on_record(self, record: Record) -> None:
        self.write_line(record_line(record, self.view))

    def write_logged(self, obj: Mapping[str, Any] | None, line: str) -> None:
        self.write_line(line)

    def write_line(self, line: str) -> None:
        """Write one already-made monitor line (used by ``mbmon export``)."""
        try:
            self._f.write(line + "\n")
        except OSError as exc:
            raise self._named(exc) from exc
        self._tick()
