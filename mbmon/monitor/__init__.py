"""The interactive terminal monitor (textual): the one live view of ``sniff``, ``proxy``,
``demo`` and ``replay --browse``.

:class:`~mbmon.monitor.feed.MonitorFeed` is the hub listener (no textual in it);
:func:`run_screen` runs a command's hub loop in a thread of its own while the
screen (:mod:`mbmon.monitor.app`, imported only here, when a screen runs) has
the terminal in the main thread; :func:`save_entries` writes kept lines in any
``-w`` format through the sinks. ``import mbmon.monitor`` imports no textual.
"""

from __future__ import annotations

import heapq
import signal
import sys
import threading
from collections.abc import Callable
from typing import Any

from mbmon.model import Record
from mbmon.monitor.feed import KEEP, Entry, MonitorFeed

__all__ = ["KEEP", "Entry", "MonitorFeed", "run_screen", "save_entries"]


def save_entries(path: str, entries: list[Entry], feed: MonitorFeed, ctx: Any) -> str:
    """Write ``entries`` (kept lines) to ``path`` in the format its suffix names, through
    the sink ``-w`` uses (:func:`mbmon.sinks.base.open_sink` with the run's ``ctx``).

    The raw chunks and events kept from the first entry's time to the last one's go
    along (``.mcap``'s raw topic, ``.pcap``'s packets), in time order with the
    records. Returns what was written, in words; raises ``SinkError`` or ``OSError``.
    """
    from mbmon.hub import hooks_of
    from mbmon.sinks.base import open_sink

    if not entries:
        raise ValueError("no lines to write")
    records = [e.record for e in entries]
    t0, t1 = records[0].ts, records[-1].ts
    inputs = feed.inputs_between(t0, t1)
    sink: Any = open_sink(path, ctx)
    hooks = hooks_of(sink)
    try:
        # inputs before records of the same time: a record is made of what came in
        merged = heapq.merge(
            ((item.ts, 0, i, item) for i, item in enumerate(inputs)),
            ((rec.ts, 1, i, rec) for i, rec in enumerate(records)),
        )
        for _ts, _what, _i, item in merged:
            if isinstance(item, Record):
                hooks.records([item])
            else:
                hooks.item(item)
    finally:
        sink.close()
    return f"wrote {len(records)} lines to {path}"


def run_screen(
    feed: MonitorFeed,
    work: Callable[[], None],
    stop: Callable[[], None],
    *,
    ctx: Any = None,
    submit: Callable[[Callable[[], Any]], None] | None = None,
    after: Callable[[], None] | None = None,
    ended_note: str = "input ended; q quits",
    display_filter: str = "",
) -> None:
    """Run ``work`` (the command's hub loop) in a thread while the screen has the terminal.

    ``stop`` is what the command does on Ctrl-C (q and Ctrl-C on the screen call it
    while the run goes on). When ``work`` returns by itself the screen stays, says
    ``ended_note``, and ``after`` (if given) runs at once in the hub's thread (the
    demo finishes its log there). SIGINT and SIGTERM still reach the command's own
    handlers; the screen closes once the run has stopped. ``w`` writes through
    ``ctx`` (a :class:`~mbmon.sinks.base.SinkContext`); with ``submit`` (the hub's)
    the write runs in the hub's thread while the hub runs. ``display_filter`` is the
    screen's first display filter (the command-line syntax; ``f`` changes it).
    Returns after the screen has closed and ``work`` has returned; what was printed
    meanwhile goes to stderr then; an exception of ``work`` is raised again here.
    """
    from mbmon.monitor.app import MonitorApp

    failed: list[BaseException] = []
    done = threading.Event()

    def target() -> None:
        try:
            work()
            if after is not None:
                after()
        except BaseException as exc:  # raised again in the main thread
            failed.append(exc)
        finally:
            feed.end()
            done.set()

    worker = threading.Thread(target=target, name="mbmon-hub", daemon=True)

    def save(path: str, entries: list[Entry]) -> str:
        if ctx is None:
            raise ValueError("nothing to write with")
        if submit is None or done.is_set():
            return save_entries(path, entries, feed, ctx)
        result: list[Any] = []
        finished = threading.Event()

        def in_hub() -> list[Any]:
            try:
                result.append(save_entries(path, entries, feed, ctx))
            except Exception as exc:
                result.append(exc)
            finally:
                finished.set()
            return []

        submit(in_hub)
        if not finished.wait(30.0) and not done.is_set():
            raise TimeoutError("the capture is too busy to write now; try again")
        if not result:  # the hub ended before it took the write: do it here
            return save_entries(path, entries, feed, ctx)
        if isinstance(result[0], Exception):
            raise result[0]
        return str(result[0])

    app = MonitorApp(
        feed,
        worker=worker,
        stop=stop,
        save=save,
        ended_note=ended_note,
        display_filter=display_filter,
    )
    old: dict[int, Any] = {}  # signal number -> the handler before the screen's

    def on_signal(signum: int, frame: Any) -> None:
        app.signalled = True
        handler = old.get(signum)
        if callable(handler):
            handler(signum, frame)
        else:
            stop()

    for sig in (signal.SIGINT, signal.SIGTERM):
        old[sig] = signal.getsignal(sig)
        signal.signal(sig, on_signal)
    worker.start()
    try:
        app.run()
    finally:
        for signum, handler in old.items():
            signal.signal(signum, handler)
        if worker.is_alive():
            stop()
            worker.join()
        if app.captured:
            sys.stderr.write("".join(app.captured))
            sys.stderr.flush()
    if failed:
        raise failed[0]
