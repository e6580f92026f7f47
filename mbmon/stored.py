"""Records as a log stored them: what ``replay`` and ``export`` hand the listeners.

A :class:`StoredRecord` is a :class:`~mbmon.model.Record` read back from an
MCAP log: it carries the monitor line and the ``read --json`` object that
:mod:`mbmon.format` made when the record was recorded, instead of the frame,
noise run, event or command they were made from. It travels the same way as a
live record (a source, the hub, the listeners' ``on_records``/``on_record``),
and :func:`mbmon.format.record_line`, :func:`~mbmon.format.record_to_json` and
:func:`~mbmon.format.record_json_bytes` give its stored text with the time
printed in the listener's ``-t`` format: so one sink, registered once in
:data:`mbmon.sinks.base.SINKS`, writes the same file from ``read -w`` and from
``export -o``.

A record cut in half by a crash at the very end of an unfinished log has its
line and no object (:attr:`StoredRecord.obj` is ``None``): formats made of the
JSON object (``.jsonl``, ``.csv``, ``.parquet``, ``--json``) leave it out
(:func:`json_less`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from mbmon.model import Record, RecordKind
from mbmon.timefmt import TimeFormat, replace_time

__all__ = ["StoredRecord", "json_less", "kind_of"]

_KINDS = {kind.value: kind for kind in RecordKind}


def kind_of(obj: Mapping[str, Any] | None) -> RecordKind:
    """The record kind a stored object names; ``EVENT`` when it names none (a
    line without its object, a kind this version does not know)."""
    kind = obj.get("kind") if obj is not None else None
    return _KINDS.get(kind, RecordKind.EVENT) if isinstance(kind, str) else RecordKind.EVENT


@dataclass(frozen=True, slots=True)
class StoredRecord(Record):
    """A record read back from a log: its stored ``read --json`` object and monitor line.

    ``kind`` is the object's (``EVENT`` without one); ``stream`` is ``None``
    (the stored object names the endpoints).
    """

    obj: Mapping[str, Any] | None = None
    line: str = ""

    def text(self, fmt: TimeFormat) -> str:
        """The monitor line with its time printed in ``fmt`` (a line with no time, such
        as a raw RTU dump's ``#12``, as stored)."""
        return replace_time(self.line, fmt.text(self.ts))

    def json(self, fmt: TimeFormat) -> dict[str, Any]:
        """The stored object with its ``line`` printed in ``fmt``; a record without
        one (cut by a crash) as ``index``, ``time`` and ``line`` only."""
        line = self.line
        new = self.text(fmt)
        obj = self.obj
        if obj is None:
            return {"index": self.index, "time": self.ts, "line": new}
        if new != line and obj.get("line") == line:
            return {**obj, "line": new}
        return dict(obj)


def json_less(record: Record) -> bool:
    """Whether ``record`` is a stored record without its JSON object (see the module
    docstring): the formats made of that object leave it out."""
    return type(record) is StoredRecord and record.obj is None
