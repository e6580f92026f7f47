"""Parquet sink (``-w FILE.parquet``, ``export -o FILE.parquet``): fleet logs a database can query.

One row per record (frames, noise, events such as timeouts and disconnects,
commands), with the fields of the one JSON record (:func:`mbmon.format.record_to_json`)
as typed columns, the frame's raw bytes, and the log's metadata (mbmon
version, source, command line, profiles, timeout, baud) as file metadata under
the key ``mbmon``. The columns (:data:`SCHEMA`) are what docs/fleet.md queries
with DuckDB; the same files go to Spark or Trino unchanged.

Rows are written in row groups of :data:`ROW_GROUP` rows, and at least every
:data:`FLUSH_EVERY` seconds of wall time while the hub ticks, so a long run's
rows reach the disk as it goes; a Parquet file is readable once it is closed
(its footer): use ``--rotate`` for files that are finished while a capture
goes on. ``export`` writes rows from the log's stored records, whose raw bytes
are rebuilt from the stored header fields and PDU (MBAP: transaction id, unit,
length; RTU: unit and CRC).

pyarrow is an optional dependency (``pip install 'mbmon[parquet]'``), imported
only when a ``.parquet`` output is opened.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from mbmon import __version__
from mbmon.format import record_to_json
from mbmon.model import Record
from mbmon.sinks.base import SinkBase, SinkContext, SinkError
from mbmon.stored import StoredRecord

__all__ = ["COLUMNS", "FLUSH_EVERY", "ROW_GROUP", "ParquetSink"]

#: Rows per row group.
ROW_GROUP = 65536
#: Seconds (wall time) at most between two row groups while rows wait.
FLUSH_EVERY = 10.0

#: (column, pyarrow type name, JSON key it comes from); see docs/fleet.md.
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("time", "timestamp", "time"),
    ("index", "int64", "index"),
    ("stream", "int32", "stream"),
    ("transport", "string", "transport"),
    ("src", "string", "src"),
    ("dst", "string", "dst"),
    ("client", "string", ""),
    ("server", "string", ""),
    ("kind", "string", "kind"),
    ("event", "string", "event"),
    ("unit", "int16", "unit"),
    ("tid", "int32", "tid"),
    ("fc", "int16", "fc"),
    ("address", "int32", "address"),
    ("count", "int32", "count"),
    ("values", "list<int32>", "values"),
    ("exception_code", "int16", "exception_code"),
    ("latency_ms", "float64", "latency_ms"),
    ("malformed", "string", "malformed"),
    ("request_index", "int64", "request_index"),
    ("notes", "list<string>", "notes"),
    ("line", "string", "line"),
    ("raw", "binary", ""),
)


def _pyarrow() -> Any:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        raise SinkError("Parquet output needs pyarrow: pip install 'mbmon[parquet]'") from None
    return pa, pq


def _schema(pa: Any) -> Any:
    types = {
        "timestamp": pa.timestamp("us", tz="UTC"),
        "int64": pa.int64(),
        "int32": pa.int32(),
        "int16": pa.int16(),
        "float64": pa.float64(),
        "string": pa.string(),
        "binary": pa.binary(),
        "list<int32>": pa.list_(pa.int32()),
        "list<string>": pa.list_(pa.string()),
    }
    return pa.schema([pa.field(name, types[kind]) for name, kind, _ in COLUMNS])


def rebuilt_raw(obj: Mapping[str, Any]) -> bytes | None:
    """The ADU bytes of a logged frame from its stored fields (MBAP header or RTU
    unit and CRC around the PDU), or a noise run's bytes; ``None`` for others."""
    pdu_hex = obj.get("pdu")
    if not isinstance(pdu_hex, str):
        return None
    try:
        pdu = bytes.fromhex(pdu_hex)
    except ValueError:
        return None
    kind = obj.get("kind")
    if kind == "noise":
        return pdu
    transport = str(obj.get("transport") or "")
    unit = obj.get("unit")
    if not isinstance(unit, int):
        return None
    if transport.startswith("rtu"):
        from mbmon.protocol.crc import add_crc

        return add_crc(bytes([unit]) + pdu)
    tid = obj.get("tid")
    if not isinstance(tid, int):
        return None
    from mbmon.protocol.mbap import encode_adu

    return encode_adu(tid, unit, pdu)


class ParquetSink(SinkBase):
    """Records as rows of a Parquet file (see the module docstring)."""

    def __init__(self, path: str | Path, ctx: SinkContext) -> None:
        pa, pq = _pyarrow()
        self.path = Path(path)
        self.ctx = ctx
        self.view = ctx.view
        self._pa = pa
        self._schema = _schema(pa).with_metadata({"mbmon": json.dumps(self._metadata())})
        self._rows: dict[str, list[Any]] = {name: [] for name, _, _ in COLUMNS}
        self._count = 0
        self._closed = False
        self._last_flush = time.monotonic()
        try:
            self._writer = pq.ParquetWriter(str(self.path), self._schema, compression="zstd")
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror or str(exc), str(self.path)) from exc

    def _metadata(self) -> dict[str, Any]:
        ctx = self.ctx
        return {
            "version": __version__,
            "source": ctx.source,
            "command_line": ctx.command_line,
            "profile_specs": ctx.profile_specs,
            "profiles": [name for name, _ in ctx.profiles],
            "timeout": ctx.timeout,
            "baud": ctx.baud,
            "robot": ctx.view.robot,
        }

    # ------------------------------------------------------------------ rows

    def _add(self, obj: Mapping[str, Any], raw: bytes | None) -> None:
        rows = self._rows
        kind = obj.get("kind")
        src, dst = obj.get("src"), obj.get("dst")
        if kind in ("response", "exception"):
            client, server = dst, src
        else:
            client, server = src, dst
        for name, _type, key in COLUMNS:
            if name == "time":
                value = obj.get("time")
                value = None if value is None else round(float(value) * 1_000_000)
            elif name == "client":
                value = client
            elif name == "server":
                value = server
            elif name == "raw":
                value = raw
            elif name == "notes":
                value = list(obj.get("notes") or [])
            else:
                value = obj.get(key)
            rows[name].append(value)
        self._count += 1
        if self._count >= ROW_GROUP:
            self._flush()

    def _flush(self) -> None:
        if not self._count:
            return
        pa = self._pa
        arrays = []
        for field in self._schema:
            values = self._rows[field.name]
            if field.name == "time":
                arrays.append(pa.array(values, type=pa.int64()).cast(field.type))
            else:
                arrays.append(pa.array(values, type=field.type))
        table = pa.Table.from_arrays(arrays, schema=self._schema)
        try:
            self._writer.write_table(table)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror or str(exc), str(self.path)) from exc
        self._rows = {name: [] for name, _, _ in COLUMNS}
        self._count = 0
        self._last_flush = time.monotonic()

    # ------------------------------------------------------------------ listener hooks

    def on_record(self, record: Record) -> None:
        raw: bytes | None = None
        if record.frame is not None:
            raw = record.frame.raw
        elif record.noise is not None:
            raw = bytes(record.noise.raw)
        elif type(record) is StoredRecord:  # read back from a log (export)
            if record.obj is None:
                return  # cut by a crash: a line, no fields to write
            raw = rebuilt_raw(record.obj)
        self._add(record_to_json(record, self.view), raw)

    def on_tick(self, now: float) -> None:
        if self._count and time.monotonic() - self._last_flush >= FLUSH_EVERY:
            self._flush()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._flush()
        finally:
            self._writer.close()
