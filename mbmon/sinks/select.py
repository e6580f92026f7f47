"""What a command shows: the filters (``--unit``, ``--fc``, ``--address``, ``--since``,
``--until``, ``--grep``) and ``-c N`` in front of the listeners that print.

:class:`Selection` is a listener that passes on only the records the filter
lets through to the listeners it wraps (the console, a live view), and asks the
run to end once ``count`` records were selected. Logs and the summary are not
behind it: they keep everything (``mbmon export`` filters a log afterwards).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from mbmon.filters import RecordFilter
from mbmon.format import View, record_line
from mbmon.hub import close_all, hooks_of
from mbmon.model import Record


def passes(flt: RecordFilter, record: Record, view: View) -> bool:
    """Whether ``flt`` lets ``record`` through; its line is made only for ``--grep``."""
    if flt.needs_line:
        return flt.matches_record(record, record_line(record, view))
    return flt.matches_record(record)


class Selection:
    """Filters and counts records for the listeners behind it."""

    name = "selection"

    def __init__(
        self,
        listeners: Iterable[Any],
        view: View,
        flt: RecordFilter | None = None,
        count: int | None = None,
        on_full: Callable[[], None] | None = None,
    ) -> None:
        self.listeners = list(listeners)
        self._hooks = [hooks_of(listener) for listener in self.listeners]
        self.view = view
        self.filter = flt if flt is not None and flt.active else None
        self.left = count
        self.on_full = on_full
        self.selected = 0

    def on_records(self, records: list[Record]) -> None:
        flt = self.filter
        if flt is not None:
            view = self.view
            records = [r for r in records if passes(flt, r, view)]
        left = self.left
        if left is not None:
            if left <= 0:
                return
            records = records[:left]
            self.left = left - len(records)
        if not records:
            return
        self.selected += len(records)
        for hooks in self._hooks:
            hooks.records(records)
        if self.left == 0 and self.on_full is not None:
            self.on_full()

    def on_tick(self, now: float) -> None:
        for hooks in self._hooks:
            hooks.tick(now)

    def close(self) -> None:
        """Close every listener behind the selection, each whatever the others do."""
        close_all(self._hooks)
