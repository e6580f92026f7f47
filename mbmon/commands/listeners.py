"""The one listener order of every command, and the one meaning of ``-c N``.

Re-exported by :mod:`mbmon.commands.common`. A command builds its outputs and
hands them to :func:`attach_outputs`, which adds them to the hub in the one
order: **logs first** (``-w`` files, the Foxglove feed), **then the screen**
(plain lines or the monitor, behind the display filter), **then the summary**.
A record that reached the screen has reached every log, whenever a signal
stops the run.

``-c N`` (:func:`add_count_option`, :class:`FrameBudget`) counts **frames that
pass the filters** (``--unit --fc --address --since --until --grep``):
Connect/Disconnect and other events do not count. Every output sees the records
up to the N-th counted frame, nothing after it: exactly N frames are shown and
the logs end at the same frame. Then the run ends (``stop``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

#: the help of ``-c`` in every command that has it
COUNT_HELP = (
    "stop after N frames that pass the filters (Connect/Disconnect and other events do "
    "not count); the screen and the logs end at the same frame"
)


def add_count_option(group: Any) -> None:
    """``-c N`` / ``--count N``: the one ``-c`` (:class:`FrameBudget` reads it)."""
    from mbmon.commands.values import positive_int

    group.add_argument("-c", "--count", type=positive_int, metavar="N", help=COUNT_HELP)


class FrameBudget:
    """Counts frame records for ``-c N``; the first listener, so it cuts each batch first.

    With filters (``flt``, active ones only) only the frames they let through
    count, as with tcpdump's ``-c`` behind its filter: ``--fc 16 -c 5`` shows five
    writes. Records without a frame (Connect, Disconnect, noise, timeouts) never
    count. The outputs behind it (:class:`Limited`) see everything up to the N-th
    counted frame, nothing after it; ``stop()`` is called once, when it is
    reached (``hub.enough`` for a file, the live loop's stop for a live run).
    """

    name = "count"

    def __init__(
        self, count: int, stop: Callable[[], Any], flt: Any = None, view: Any = None
    ) -> None:
        self.left = count
        self._stop = stop
        self._filter = flt if flt is not None and flt.active else None
        self._view = view
        self.done = False
        self._batch: list[Any] | None = None
        self._cut: list[Any] = []

    def counts(self, record: Any) -> bool:
        """Whether ``record`` is one of the N: a frame the filters let through."""
        if record.frame is None:
            return False
        flt = self._filter
        if flt is None:
            return True
        from mbmon.sinks.select import passes

        return passes(flt, record, self._view)

    def on_records(self, records: list[Any]) -> None:
        if self.done:
            self._batch, self._cut = records, []
            return
        keep = len(records)
        for i, record in enumerate(records):
            if self.counts(record):
                self.left -= 1
                if self.left <= 0:
                    keep = i + 1
                    self.done = True
                    self._stop()
                    break
        self._batch, self._cut = records, records[:keep]

    def allowed(self, records: list[Any]) -> list[Any]:
        """The part of the batch ``records`` an output behind the budget gets."""
        return self._cut if records is self._batch else ([] if self.done else records)


class Limited:
    """An output behind a :class:`FrameBudget`: it sees nothing after the N-th frame
    (records, chunks and events alike); ticks and ``close`` always reach it."""

    def __init__(self, inner: Any, budget: FrameBudget) -> None:
        from mbmon.hub import hooks_of

        self.inner = inner
        self.budget = budget
        self.name = getattr(inner, "name", None) or getattr(inner, "path", None)
        self._hooks = hooks_of(inner)

    def on_records(self, records: list[Any]) -> None:
        records = self.budget.allowed(records)
        if records:
            self._hooks.records(records)

    def on_chunk(self, chunk: Any) -> None:
        if not self.budget.done:
            self._hooks.item(chunk)

    def on_event(self, event: Any) -> None:
        if not self.budget.done:
            self._hooks.item(event)

    def on_tick(self, now: float) -> None:
        self._hooks.tick(now)

    def close(self) -> None:
        if self._hooks.close is not None:
            self._hooks.close()


def attach_outputs(
    hub: Any,
    *,
    logs: Iterable[Any] = (),
    screen: Any = None,
    summary: Any = None,
    budget: FrameBudget | None = None,
    gate: Any = None,
) -> None:
    """Add a command's outputs to ``hub`` in the one order: ``logs`` (``-w`` sinks,
    the Foxglove feed), then ``screen`` (the console or the monitor, already behind
    its display filter: :class:`~mbmon.sinks.select.Selection`), then ``summary``.

    With a ``gate`` (``--trigger``'s :class:`~mbmon.analysis.trigger.TriggerGate`)
    the logs and the screen are added to it and it takes their place; the summary
    counts everything. With a ``budget`` (``-c N``) it is added first and every
    output sits behind it (:class:`Limited`). ``None`` entries are skipped, so a
    command passes ``screen=None`` for ``-q``. Listeners a command adds after
    this (health figures, the monitor's figures) come after the summary."""
    outputs: list[Any] = []
    front = [out for out in (*logs, screen) if out is not None]
    if gate is not None:
        for out in front:
            gate.add(out)
        outputs.append(gate)
    else:
        outputs.extend(front)
    if summary is not None:
        outputs.append(summary)
    if budget is not None:
        hub.add_listener(budget)
        outputs = [Limited(out, budget) for out in outputs]
    for out in outputs:
        hub.add_listener(out)
