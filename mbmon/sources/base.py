"""The source contract: what every source of a run is, and how the hub drives it.

A *source* turns something outside mbmon (a capture file, a raw RTU dump, a
network interface, one or two serial taps, the proxy, an MCAP log, the bytes a
user typed) into the hub's input: :class:`~mbmon.model.Chunk` and
:class:`~mbmon.model.Event` items. Sources are thin: they own their resource
(a file, a socket, a port, a child process) and nothing of the flow after it.
The hub owns the loop and, for files, the thread: a source never runs the
pipeline or calls a listener.

The contract (:class:`Source`), in the order a command uses it:

``name``
    How the source is named in banners, summaries and log metadata
    (``eth0``, ``/dev/ttyUSB0+/dev/ttyUSB1``, ``cell.pcapng``).
``mode``
    How the hub takes the input (:data:`SourceMode`):

    * ``"file"``: :meth:`Source.items` is read in the caller's thread, as fast
      as it goes; the capture's own time drives everything
      (:meth:`~mbmon.hub.Hub.run_items`).
    * ``"stream"``: :meth:`Source.items` may wait between items (a pipe, a
      FIFO, a paced replay): it is read in a thread of its own and the hub
      ticks its listeners while it waits, at the capture's time
      (:func:`mbmon.sources.pipe.feed_pipe`).
    * ``"live"``: :meth:`Source.start` starts the source's own threads (or an
      asyncio loop, or a child process's reader), which hand items to the hub
      with the thread-safe :meth:`~mbmon.hub.Hub.put` and
      :meth:`~mbmon.hub.Hub.submit`; the hub's loop (:meth:`~mbmon.hub.Hub.run`)
      runs until a signal, the source (``hub.stop()``) or ``-c`` ends it.
``open(hub)``
    Acquire the resource now, before any output is opened, so that a source
    that cannot start leaves no files behind. Get stream ids from
    ``hub.new_stream``; register stages that need time with ``hub.add_ticker``
    and listeners of the source's own (bus health) with ``hub.add_listener``.
    Raise :class:`SourceError` with one line for the user when it cannot open
    (no such file, no permission, no such interface): never a traceback.
``start()``
    Begin delivering (live sources); nothing for file and stream sources.
``items()``
    The items, in order (file and stream sources); ``()`` for live ones.
    Damage in the input is an ``ERROR`` event without a stream (the hub counts
    it in ``hub.errors``), not an exception.
``stop()``
    Stop delivering and release the resource; idempotent, safe from any state
    (also when :meth:`~Source.start` never ran).
``stats()``
    Figures of the source for the live screen's header (flat ``name: value``);
    called in the hub's thread while the run goes on.
``closing(ts)``
    The events that close the source's part of a log (a ``STATS`` event with
    the kernel's drop counters, the bus health figures), fed once after
    :meth:`~Source.stop` unless the run ended early (``-c`` reached).
``summary()``
    Lines for the closing summary on stderr (what the source saw: packets,
    reads, drops), each without indentation.

:class:`BaseSource` implements every method as "nothing"; a source subclasses
it and overrides what it has. :func:`run_sources` is the one run path every
command uses: start, the hub's loop for the sources' mode, stop, the closing
events. Listeners are the command's (logs first, then the screen, then the
summary); :meth:`~mbmon.hub.Hub.close` stays the command's too, so a command
can close its outputs after the summary figures were fed.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

if TYPE_CHECKING:  # annotations only: a file the compiled core reads never needs the hub
    from mbmon.hub import Hub, Item
    from mbmon.model import Event

__all__ = ["BaseSource", "Source", "SourceError", "SourceMode", "run_sources"]

SourceMode = Literal["file", "stream", "live"]


class SourceError(Exception):
    """A source cannot open: one line for the user (the command exits with status 1)."""


@runtime_checkable
class Source(Protocol):
    """One source of a run (see the module docstring for each member)."""

    name: str
    mode: SourceMode

    def open(self, hub: Hub) -> None: ...

    def start(self) -> None: ...

    def items(self) -> Iterable[Item]: ...

    def stop(self) -> None: ...

    def stats(self) -> dict[str, Any]: ...

    def closing(self, ts: float) -> list[Event]: ...

    def summary(self) -> list[str]: ...


class BaseSource:
    """Every member of :class:`Source` as "nothing": subclass it, override what you have.

    :meth:`open` keeps the hub in :attr:`hub` for the subclass.
    """

    name: str = "source"
    mode: SourceMode = "file"

    def __init__(self) -> None:
        self.hub: Hub | None = None

    def open(self, hub: Hub) -> None:
        """Keep ``hub``; a subclass acquires its resource and calls this first."""
        self.hub = hub

    def start(self) -> None:
        """Nothing to start (a file or stream source)."""

    def items(self) -> Iterable[Item]:
        """No items of its own (a live source)."""
        return ()

    def stop(self) -> None:
        """Nothing to release."""

    def stats(self) -> dict[str, Any]:
        """No figures for the screen."""
        return {}

    def closing(self, ts: float) -> list[Event]:
        """No closing events."""
        return []

    def summary(self) -> list[str]:
        """No summary lines."""
        return []


def run_sources(
    hub: Hub,
    sources: Sequence[Source],
    stop: threading.Event | None = None,
    *,
    clock: Callable[[], float] | None = None,
) -> None:
    """Run ``sources`` (already :meth:`~Source.open`) through ``hub`` to their end.

    File sources are read one after another in the calling thread, stream
    sources through a reader thread with ticks while they wait, live sources
    are started and the hub's loop runs until ``stop`` is set or
    :meth:`~mbmon.hub.Hub.stop` is called (a signal, a source whose input
    ended, ``-c``); the loop then stops the sources in its own thread and feeds
    what they queued before it finishes, so nothing delivered is lost. Every
    source is stopped whatever happens (again: ``stop`` is idempotent), and their
    :meth:`~Source.closing` events are fed at ``clock()`` (default: the hub's
    clock) unless the run ended early (``hub.done``). The pipeline is finished;
    the listeners are not closed (``hub.close()`` is the caller's).
    """
    modes = {source.mode for source in sources}
    if "live" in modes and len(modes) > 1:
        raise ValueError("live sources cannot be mixed with file or stream sources")
    try:
        if "live" in modes:
            for source in sources:
                source.start()
            hub.run(stop, on_stop=lambda: _stop_all(sources))
        else:
            _pull(hub, sources)
    finally:
        _stop_all(sources)
    if hub.done:
        return
    now = clock() if clock is not None else hub.clock()
    for source in sources:
        for event in source.closing(now):
            hub.feed(event)


def _stop_all(sources: Sequence[Source]) -> None:
    """Stop every source, whatever the others do (the first failure is raised last)."""
    failure: Exception | None = None
    for source in sources:
        try:
            source.stop()
        except Exception as exc:
            failure = failure or exc
    if failure is not None:
        raise failure


def _pull(hub: Hub, sources: Sequence[Source]) -> None:
    """File and stream sources, in order, each to its end (or until ``hub.done``); each
    is decoded as it is alone (:meth:`~mbmon.hub.Hub.end_of_input` between two), on
    stream ids of its own (the hub's)."""
    from mbmon.sources.pipe import feed_pipe

    for n, source in enumerate(sources):
        if hub.done:
            break
        if n:
            hub.end_of_input()
        if source.mode == "stream":
            feed_pipe(hub, source.items(), finish=False)
        else:
            hub.feed_items(source.items())
    hub.finish()
