"""An MCAP log as the source of a run: ``replay`` and ``export`` through the hub.

:class:`LogSource` yields what a log holds in capture order, filtered and
paced: its stored records (:class:`~mbmon.stored.StoredRecord`, the lines and
objects made when it was recorded) or, to decode them again (``replay
--redecode``), the chunks and source events of ``/modbus/raw``. It feeds the
same :class:`~mbmon.hub.Hub` and listeners as ``read`` (the console, a sink
opened by suffix, the live Foxglove feed): stored records through
:class:`StoredPipeline`, which passes them on as they come (they are decoded
already), raw items through the ordinary :class:`~mbmon.pipeline.Pipeline`.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, Literal, cast

from mbmon.filters import Pacer, RecordFilter
from mbmon.hub import Hub, Item
from mbmon.io.mcap.reader import McapLog
from mbmon.io.replay import logged_records, raw_items
from mbmon.model import Chunk, Event, Record
from mbmon.pipeline import Pipeline
from mbmon.sources.base import BaseSource
from mbmon.stored import StoredRecord
from mbmon.timefmt import TimeFormat

__all__ = ["LogSource", "StoredPipeline", "run_stored"]


class StoredPipeline(Pipeline):
    """The middle of a run over stored records: each is a record already, passed on
    as it comes; nothing is pending, so ticks and the end add nothing. Anything
    else (the hub's notice about a detached listener, which stderr shows too)
    makes no record."""

    def feed(self, item: Chunk | Event) -> list[Record]:
        fed: object = item  # a stored record, handed in as the hub's input (run_stored)
        if type(fed) is StoredRecord:
            return [fed]
        return []

    def tick(self, now: float) -> list[Record]:
        return []

    def next_deadline(self) -> float | None:
        return None

    def finish(self, ts: float | None = None) -> list[Record]:
        return []


class LogSource(BaseSource):
    """The records of a log (or, with ``raw``, its raw chunks and source events),
    filtered and paced (see the module docstring).

    ``flt`` keeps the stored records it matches (their line and object with the
    time printed in ``fmt``, as shown); a re-decode's records are filtered after
    the pipeline, by the listener that shows them
    (:class:`~mbmon.sinks.select.Selection`): every raw item is fed, and only
    those inside ``--since``/``--until`` are paced. ``pacer`` holds every item back to its due
    time (``--speed``). ``need_json`` leaves out the stored records that have no
    ``read --json`` object (cut by a crash: ``replay --json`` prints objects only).
    """

    def __init__(
        self,
        log: McapLog,
        fmt: TimeFormat,
        flt: RecordFilter | None = None,
        *,
        pacer: Pacer | None = None,
        raw: bool = False,
        need_json: bool = False,
    ) -> None:
        super().__init__()
        self.log = log
        self.name = str(log.path)
        #: how the hub takes it (the source contract's modes): paced input waits
        self.mode: Literal["file", "stream"] = "stream" if pacer is not None else "file"
        self.fmt = fmt
        self.filter = flt if flt is not None and flt.active else None
        self.pacer = pacer
        self.raw = raw
        self.need_json = need_json

    def items(self) -> Iterator[Any]:
        """What the hub is fed: stored records, or raw items with ``raw``."""
        return self._raw_items() if self.raw else self._stored()

    def _stored(self) -> Iterator[StoredRecord]:
        flt, fmt, pacer, need_json = self.filter, self.fmt, self.pacer, self.need_json
        for logged in logged_records(self.log):
            record = logged.stored()
            if need_json and record.obj is None:
                continue
            if flt is not None:
                obj = record.json(fmt) if record.obj is not None else None
                if not flt.matches(obj, record.text(fmt), record.ts):
                    continue
            if pacer is not None:
                pacer.wait(record.ts)
            yield record

    def _raw_items(self) -> Iterator[Item]:
        flt, pacer = self.filter, self.pacer
        since = flt.since if flt is not None else None
        until = flt.until if flt is not None else None
        items: Iterator[Item] = raw_items(self.log)
        if self.hub is not None:  # opened on a hub: its recorded ids become the run's
            items = self.hub.recorded_streams().items(items)
        for item in items:
            # every item is decoded (a request before --since pairs an answer after
            # it); only those inside the shown span are paced
            if pacer is not None and not (
                (since is not None and item.ts < since) or (until is not None and item.ts > until)
            ):
                pacer.wait(item.ts)
            yield item


def run_stored(hub: Hub, source: LogSource) -> None:
    """Feed ``source``'s stored records to ``hub`` (built on a :class:`StoredPipeline`)
    and finish: the hub's input is chunks and events, and a stored record passes
    through its pipeline as both are fed."""
    hub.run_items(cast(Iterator[Item], source.items()))
