"""CSV sink (``-w FILE.csv``): one row per Modbus frame (and per noise run), for spreadsheets.

Owns the CSV column set: the ``read --json`` keys of a frame, with lists
flattened (``values`` space separated, ``notes`` joined by `` | ``), plus an
ISO 8601 UTC time. Events and reconstructed commands are not rows.
"""

from __future__ import annotations

import csv
import datetime as _dt
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from mbmon.format import record_to_json
from mbmon.model import Record, RecordKind
from mbmon.sinks.base import SinkContext
from mbmon.sinks.jsonl import TextFileSink
from mbmon.timefmt import CALENDAR_MAX, CALENDAR_MIN, epoch_text

COLUMNS = (
    "index", "time", "utc", "stream", "src", "dst", "transport", "tid", "unit", "fc", "kind",
    "exception_code", "address", "count", "values", "pdu", "crc_ok", "latency_ms", "malformed",
    "request_index", "notes", "line",
)  # fmt: skip

#: record kinds that become rows
_ROW_RECORDS = frozenset(
    {RecordKind.REQUEST, RecordKind.RESPONSE, RecordKind.EXCEPTION, RecordKind.NOISE}
)


def utc_text(ts: float) -> str:
    """ISO 8601 UTC with microseconds: ``2024-05-01T12:00:00.123456Z``; a time no
    calendar shows (year 55840, NaN) as epoch seconds (:func:`mbmon.timefmt.epoch_text`)."""
    if not CALENDAR_MIN <= ts < CALENDAR_MAX:
        return epoch_text(ts)
    try:
        moment = _dt.datetime.fromtimestamp(ts, _dt.UTC)
    except (OverflowError, OSError, ValueError):
        return epoch_text(ts)
    return moment.strftime("%Y-%m-%dT%H:%M:%S.%f") + "Z"


def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    return value


def csv_row(obj: Mapping[str, Any]) -> list[Any]:
    """The CSV row of one ``read --json`` object."""
    values = obj.get("values")
    notes = obj.get("notes")
    row = dict(obj)
    row["utc"] = utc_text(obj["time"]) if obj.get("time") is not None else ""
    row["values"] = " ".join(str(v) for v in values) if values else ""
    row["notes"] = " | ".join(notes) if notes else ""
    return [_cell(row.get(col)) for col in COLUMNS]


class CsvSink(TextFileSink):
    """A header row, then one row per frame or noise record."""

    def __init__(self, path: str | Path, ctx: SinkContext) -> None:
        super().__init__(path, ctx, newline="")
        self._csv = csv.writer(self._f)
        try:
            self._csv.writerow(COLUMNS)
        except OSError as exc:
            raise self._named(exc) from exc

    def on_record(self, record: Record) -> None:
        if record.kind in _ROW_RECORDS:
            try:
                self._csv.writerow(csv_row(record_to_json(record, self.view)))
            except OSError as exc:
                raise self._named(exc) from exc
            self._tick()
