"""A capture that arrives through a pipe (``tcpdump -w - | mbmon read -``), fed to a hub
that keeps ticking while the pipe is silent.

A file is read in the caller's thread, as fast as it goes (:meth:`Hub.run_items`).
A pipe, FIFO or serial device can stall for minutes between packets, and a read
blocked on it would leave the console and every ``-w`` log holding what they
buffered. :func:`feed_pipe` reads the items in a thread of their own and feeds
them to the hub in the caller's thread, and ticks the hub every quarter second
of wall time, whether items come or not, so listeners flush (every log on disk
within a second) and the pipeline settles what the capture's own time already
completes.

Time stays the capture's: a stall is no evidence that an answer is missing
(``tcpdump -w -`` without ``-U`` holds whole packets in its buffer), so the hub
is ticked at the newest capture time it has seen, never at the wall clock.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterable
from typing import Any

from mbmon.hub import BATCH, LISTENER_TICK, Hub, Item


class _End:
    """The reader's last word: the items ended (``error`` when the reader raised)."""

    def __init__(self, error: BaseException | None = None) -> None:
        self.error = error


def feed_pipe(
    hub: Hub, items: Iterable[Item], *, every: float = LISTENER_TICK, finish: bool = True
) -> None:
    """Feed ``items`` (read as they come from a pipe) to ``hub``, ticking it every
    ``every`` seconds while none arrive; then finish the pipeline, as
    :meth:`Hub.run_items` does. An exception of the reader is raised here; so is a
    ``KeyboardInterrupt`` arriving while this waits. Stops early once
    :attr:`Hub.done` (every listener gone, or ``-c N`` reached). ``finish=False``
    leaves the pipeline open (more sources follow: :func:`mbmon.sources.base.run_sources`)."""
    inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()

    def read() -> None:
        try:
            for item in items:
                inbox.put(item)
        except BaseException as exc:  # handed to the hub's thread, raised there
            inbox.put(_End(exc))
        else:
            inbox.put(_End())

    reader = threading.Thread(target=read, name="mbmon-pipe-reader", daemon=True)
    reader.start()
    end: _End | None = None
    next_tick = time.monotonic() + every
    while end is None and not hub.done:
        try:
            first = inbox.get(timeout=max(0.0, next_tick - time.monotonic()))
        except queue.Empty:
            first = None
        if first is None or time.monotonic() >= next_tick:
            next_tick = time.monotonic() + every
            hub.tick(hub.now)  # flush what waits, at the capture's time (never the clock's)
        if first is None:
            continue
        batch: list[Item] = []
        item = first
        while True:
            if isinstance(item, _End):
                end = item
                break
            batch.append(item)
            if len(batch) >= BATCH:
                break
            try:
                item = inbox.get_nowait()
            except queue.Empty:
                break
        if batch:
            hub.feed_items(batch)
    if end is not None and end.error is not None:
        raise end.error
    if finish:
        hub.finish()
