"""Triggers with a pre-trigger buffer: ``--trigger EXPR --before 30s --after 10s``.

This module owns the decision what of a run is kept: :class:`TriggerGate` is one
hub listener standing in front of the run's logs and screen. It holds the last
``before`` seconds (capture time) of input chunks, events and records; when a
record matches the trigger expression (the grammar of
:func:`mbmon.filters.parse_expression`, the same parser the display filter
``--where`` uses), it opens a window from ``before`` seconds before that record
to ``after`` seconds after it, hands the held items of the window to its
listeners, in order, and then everything that comes until the window ends. A
record matching while a window is open extends it (``after`` from that
record). When a window ends, every listener that can (a rotating sink,
:class:`mbmon.analysis.rotate.RotatingSink`) finishes its file, so each window
is a file of its own; the ``on_window`` callback is told the window's trigger
time, start, end and what matched (``read`` and ``sniff`` print it on stderr).

Outside windows nothing reaches the listeners. The buffer is bounded by
``before`` seconds and by ``max_held`` items (the oldest go first).

A listener behind the gate that raises takes the gate with it: the hub
reports the failure and detaches the gate (the run's exit status says an
output failed), as it would for that listener alone; the gate's ``close``
still closes every listener behind it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mbmon.filters import Expression
from mbmon.hub import Hooks, close_all, hooks_of
from mbmon.model import Record

__all__ = ["MAX_HELD", "TriggerGate", "Window"]

#: Items held before a trigger at most (chunks, events and records).
MAX_HELD = 1_000_000


@dataclass(slots=True)
class Window:
    """One kept window: the first trigger's record time and line, and the span
    kept (``end`` moves on while further triggers come)."""

    trigger: float
    start: float
    end: float
    what: str
    triggers: int = 1


class TriggerGate:
    """The listeners behind one trigger (see the module docstring).

    Add the listeners with :meth:`add` (in the order the hub would call them:
    logs first, then the screen), then the gate to the hub.
    """

    name = "trigger"

    def __init__(
        self,
        expression: Expression,
        before: float,
        after: float,
        *,
        on_window: Callable[[int, Window], None] | None = None,
        max_held: int = MAX_HELD,
    ) -> None:
        self.expression = expression
        self.before = before
        self.after = after
        self.on_window = on_window
        self._held: deque[tuple[float, int, Any]] = deque(maxlen=max_held)
        self._targets: list[tuple[Any, Hooks]] = []
        self._open: Window | None = None
        self._latest = float("-inf")
        #: the windows kept so far, in order
        self.windows: list[Window] = []

    def add(self, listener: Any) -> None:
        """A listener behind the gate; its hooks are looked up now, as the hub does."""
        self._targets.append((listener, hooks_of(listener)))

    @property
    def listeners(self) -> list[Any]:
        return [listener for listener, _ in self._targets]

    # ------------------------------------------------------------------ hub hooks

    def on_chunk(self, chunk: Any) -> None:
        self._item(chunk.ts, 0, chunk)

    def on_event(self, event: Any) -> None:
        self._item(event.ts, 1, event)

    def on_records(self, records: list[Record]) -> None:
        matches = self.expression.matches_record
        for record in records:
            if matches(record):
                self._trigger(record)
            self._item(record.ts, 2, record)

    def on_tick(self, now: float) -> None:
        window = self._open
        if window is not None and now > window.end:
            self._close_window()
        self._prune(now)
        for _listener, hooks in self._targets:
            hooks.tick(now)

    def close(self) -> None:
        """The run ended: an open window ends here; every listener is closed,
        each whatever the others do (the first failure is raised after)."""
        if self._open is not None:
            self._close_window()
        close_all(hooks for _listener, hooks in self._targets)

    # ------------------------------------------------------------------ internals

    def _trigger(self, record: Record) -> None:
        ts = record.ts
        window = self._open
        if window is not None and ts <= window.end:
            window.end = max(window.end, ts + self.after)
            window.triggers += 1
            return
        if window is not None:
            self._close_window()
        from mbmon.format import View, record_to_json

        line = record_to_json(record, View()).get("line") or ""
        window = Window(ts, ts - self.before, ts + self.after, line)
        self._open = window
        held = self._held
        while held:
            item_ts, kind, item = held.popleft()
            if item_ts >= window.start:
                self._deliver(kind, item)

    def _item(self, ts: float, kind: int, item: Any) -> None:
        if ts > self._latest:
            self._latest = ts
        window = self._open
        if window is not None:
            if ts <= window.end:
                self._deliver(kind, item)
                return
            self._close_window()
        self._held.append((ts, kind, item))
        self._prune(self._latest)

    def _prune(self, now: float) -> None:
        held = self._held
        limit = now - self.before
        while held and held[0][0] < limit:
            held.popleft()

    def _deliver(self, kind: int, item: Any) -> None:
        for _listener, hooks in self._targets:
            if kind == 2:
                hooks.records([item])
            else:
                hooks.item(item)

    def _close_window(self) -> None:
        window = self._open
        assert window is not None
        self._open = None
        self.windows.append(window)
        for listener, _hooks in self._targets:
            end_file = getattr(listener, "end_file", None)
            if callable(end_file):
                end_file()
        if self.on_window is not None:
            self.on_window(len(self.windows), window)
