"""The engine's way to the hub: :class:`Observer` hands copies of the traffic (chunks)
and the engine's events to the hub's thread-safe queue, in batches, and skips
chunks (counted, then reported) while the hub is more than ``max_backlog`` items
behind, so that observation never holds forwarding up and memory stays bounded.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol

from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport, fast_constructor
from mbmon.proxy.config import MAX_BACKLOG

__all__ = ["Meter", "Observer"]

_new_chunk = fast_constructor(Chunk)  # two per request: about twice as fast as Chunk(...)


class Meter(Protocol):
    """What the observer reads to know its backlog: items taken so far."""

    seen: int


class Observer:
    """The engine's way to the hub: ``put`` (thread-safe), ``new_stream``, the clock.

    Chunks are skipped (and counted) while the hub is more than ``max_backlog``
    items behind; events always go through (they are few). ``meter`` tells how
    far behind: anything whose ``seen`` counts the items taken so far (the hub
    itself, :attr:`mbmon.hub.Hub.seen`; in the forwarding process, the pipe).

    Once :meth:`bind` gives it a scheduler (the loop's ``call_soon``, or a
    ``call_later`` of :attr:`ProxyConfig.handover`) and a ``submit``
    (``hub.submit``), items wait in a batch that is handed over after the
    forwarding that made them: one queue operation and one wake-up of the hub's
    thread per batch instead of per chunk.
    """

    def __init__(
        self,
        put: Callable[[Chunk | Event], None],
        new_stream: Callable[[Transport, str, str], Stream],
        *,
        meter: Meter | None = None,
        max_backlog: int = MAX_BACKLOG,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self._put = put
        self.new_stream = new_stream
        self.clock = clock
        self._meter = meter
        self._max_backlog = max_backlog
        self.sent = 0
        self.skipped = 0
        self._skipping = 0
        self._batch: list[Chunk | Event] = []
        self._call_soon: Callable[[Callable[[], None]], Any] | None = None
        self._submit: Callable[[Callable[[], list[Chunk | Event]]], None] | None = None

    def bind(
        self,
        call_soon: Callable[[Callable[[], None]], Any],
        submit: Callable[[Callable[[], list[Chunk | Event]]], None] | None = None,
    ) -> None:
        """Batch items until ``call_soon(flush)`` runs (``loop.call_soon``: this loop
        iteration; a ``call_later``: after a delay) and hand them over with ``submit``
        (in the loop's thread only); without ``submit``, items go one by one to
        ``put`` (an observer that hands batches over itself needs only the timer)."""
        self._call_soon = call_soon
        self._submit = submit

    def flush(self) -> None:
        """Hand the waiting batch over now."""
        batch = self._batch
        if batch and self._submit is not None:
            self._batch = []
            self._submit(lambda: batch)

    def _emit(self, item: Chunk | Event) -> None:
        call_soon = self._call_soon
        if call_soon is None or self._submit is None:
            self._put(item)
            return
        batch = self._batch
        batch.append(item)
        if len(batch) == 1:
            call_soon(self.flush)

    def chunk(self, stream: Stream, direction: Direction, data: bytes, ts: float) -> None:
        if self._admit(ts):
            self._emit(_new_chunk(ts, stream, direction, data))

    def _admit(self, ts: float) -> bool:
        """Whether a chunk at ``ts`` is observed (counted as sent): not while the hub
        is more than ``max_backlog`` behind (skipped, counted); the first one after a
        skip comes after a NOTICE that says how many were not observed."""
        meter = self._meter
        if meter is not None and self.sent - meter.seen > self._max_backlog:
            self.skipped += 1
            self._skipping += 1
            return False
        if self._skipping:
            n, self._skipping = self._skipping, 0
            self.event(
                None,
                EventKind.NOTICE,
                {"message": f"{n} chunks were forwarded but not observed: the monitor fell behind"},
                ts,
            )
        self.sent += 1
        return True

    def event(
        self, stream: Stream | None, kind: EventKind, info: dict[str, Any], ts: float | None = None
    ) -> None:
        self.sent += 1
        self._emit(Event(self.clock() if ts is None else ts, stream, kind, info))
