"""Text sink (``-w FILE.txt``): the monitor lines exactly as the console prints them.

One line per record, as the robot's Modbus Monitor would export them: time,
label, function code + data in hex, then the notes. A record read back from a
log (``mbmon export``) has its stored line, with the time in this file's ``-t``
format (:class:`~mbmon.stored.StoredRecord`).
"""

from __future__ import annotations

from mbmon.format import record_line
from mbmon.model import Record
from mbmon.sinks.jsonl import TextFileSink


class TextSink(TextFileSink):
    """The console's monitor line for every record."""

    def on_record(self, record: Record) -> None:
        try:
            self._f.write(record_line(record, self.view) + "\n")
        except OSError as exc:
            raise self._named(exc) from exc
        self._tick()
