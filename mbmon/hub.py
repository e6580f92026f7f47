"""The one loop of a run: sources in, pipeline in the middle, listeners out.

A :class:`Hub` owns one run of any command (``read``, ``replay --redecode``,
``sniff``, ``proxy``, ``demo``). Sources (the contract of :mod:`mbmon.sources.base`,
run by its ``run_sources``) hand it chunks and events; it feeds the
:class:`~mbmon.pipeline.Pipeline`, fans the records out to its listeners, moves
time on (``tick``) and closes everything in order. Model: python-can's
``Notifier`` and mitmproxy's addons.

Two ways in:

* :meth:`Hub.feed` / :meth:`Hub.run_items`: the caller's own thread (files,
  whose time is the capture's).
* :meth:`Hub.put` / :meth:`Hub.submit`: thread-safe, from source threads
  (pyserial, scapy) or an asyncio loop (the proxy); :meth:`Hub.run` takes them
  from one queue in one thread, so the pipeline, the formatter's caches and the
  listeners are only ever touched from that thread. ``submit(fn)`` runs ``fn``
  in the hub's thread and feeds what it returns: that is how a live capture
  runs the packet dissector (whose TCP reassembly is hub-thread state).

The listener contract lives here, and only here: a listener is any object
with any of the optional hooks in :data:`HOOKS`, called only where defined:
``on_chunk(chunk)`` and ``on_event(event)`` for input as the sources gave it,
``on_records(records)`` (a batch, when the listener wants one call per batch)
or else ``on_record(record)``, ``on_tick(now)``, and ``close()``. No hook is
required. :func:`hooks_of` looks a listener's hooks up once (:class:`Hooks`);
the hub uses it, and so does every listener that wraps others (the selection of
what is shown, ``sniff``'s ``-c`` budget, a trigger's gate, a rotating sink),
so a new hook is added here and nowhere else. A listener that raises is
reported once (stderr and an ``/mbmon/events`` notice to the others) and
detached; the sources and the other listeners go on. Broken pipes
(``mbmon read … | head``) detach the listener quietly.

Time: for files, the capture's; for live sources, the packets' own timestamps,
and the wall clock only to move time on while nothing arrives (:meth:`run`).
Stateful stages say when they next need a tick (``next_deadline()``), so the
live loop sleeps until then.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import IO, Any, Protocol

from mbmon.model import Chunk, Event, EventKind, Record, Stream, Transport
from mbmon.pipeline import Pipeline
from mbmon.stream_ids import RecordedStreams, StreamIds

Item = Chunk | Event
Producer = Callable[[], Iterable[Item]]

#: The optional hooks of a listener (the one list; see the module docstring).
HOOKS = ("on_chunk", "on_event", "on_records", "on_record", "on_tick", "close")
#: The hooks the hub indexes one by one (records keep each listener's batch-or-single choice).
_INDEXED = ("on_chunk", "on_event", "on_tick")

#: How often listeners' ``on_tick`` runs on a live stream (text flushed within 0.5 s).
LISTENER_TICK = 0.25
#: The longest a live loop sleeps without looking at the clock.
MAX_SLEEP = 0.5
#: A live loop takes up to this many queued items before it looks at the clock again.
BATCH = 1000
#: and looks at deadlines at most this often (seconds).
CHECK_EVERY = 0.02


class Ticking(Protocol):
    """A stage outside the pipeline that needs time (the packet dissector's reassembly)."""

    def tick(self, now: float) -> Iterable[Item]: ...

    def next_deadline(self) -> float | None: ...


@dataclass(frozen=True, slots=True)
class Hooks:
    """A listener's bound hooks, ``None`` where it has none; ``on_record`` is
    ``None`` when the listener has ``on_records`` (the batch hook wins)."""

    on_chunk: Callable[[Chunk], Any] | None = None
    on_event: Callable[[Event], Any] | None = None
    on_records: Callable[[list[Record]], Any] | None = None
    on_record: Callable[[Record], Any] | None = None
    on_tick: Callable[[float], Any] | None = None
    close: Callable[[], Any] | None = None

    @property
    def takes_records(self) -> bool:
        """Whether the listener wants records at all (``on_records`` or ``on_record``)."""
        return self.on_records is not None or self.on_record is not None

    def records(self, records: list[Record]) -> None:
        """Hand ``records`` over: the batch hook at once, or ``on_record`` per record."""
        if self.on_records is not None:
            self.on_records(records)
        elif self.on_record is not None:
            for record in records:
                self.on_record(record)

    def item(self, item: Item) -> None:
        """Hand a source's chunk or event over (``on_chunk`` or ``on_event``)."""
        if isinstance(item, Chunk):
            if self.on_chunk is not None:
                self.on_chunk(item)
        elif self.on_event is not None:
            self.on_event(item)

    def tick(self, now: float) -> None:
        """Call ``on_tick(now)`` where the listener has it."""
        if self.on_tick is not None:
            self.on_tick(now)


def hooks_of(listener: Any) -> Hooks:
    """The hooks ``listener`` has (see :data:`HOOKS`), looked up once: what the hub
    calls, and what a listener that wraps others calls on them."""
    found: dict[str, Callable[..., Any] | None] = {}
    for hook in HOOKS:
        fn = getattr(listener, hook, None)
        found[hook] = fn if callable(fn) else None
    if found["on_records"] is not None:
        found["on_record"] = None
    return Hooks(**found)


def close_all(listeners: Iterable[Hooks]) -> None:
    """Close each listener that has ``close``, whatever the others do; the first
    failure is raised once all were closed (a wrapper's own ``close``)."""
    failure: BaseException | None = None
    for hooks in listeners:
        if hooks.close is None:
            continue
        try:
            hooks.close()
        except Exception as exc:
            failure = failure or exc
    if failure is not None:
        raise failure


@dataclass
class _Slot:
    """One attached listener and its bound hooks (``None`` where it has none)."""

    listener: Any
    name: str
    hooks: Hooks


class _Collector:
    """Keeps the records of a run in a list (:meth:`Hub.iter_records`)."""

    name = "records"

    def __init__(self, into: list[Record]) -> None:
        self.on_records = into.extend


class _Stop:
    """The queue's end marker."""


_STOP = _Stop()


def listener_name(listener: Any) -> str:
    """How a listener is named in reports: its ``name`` or its path, else its class."""
    name = getattr(listener, "name", None) or getattr(listener, "path", None)
    return str(name) if name else type(listener).__name__


class Hub:
    """Drives one run: feeds the pipeline, fans records out, ticks, isolates and closes."""

    def __init__(
        self,
        pipeline: Pipeline | None = None,
        listeners: Iterable[Any] = (),
        *,
        stderr: IO[str] | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.pipeline = pipeline if pipeline is not None else Pipeline()
        self._slots: list[_Slot] = []
        # per-hook call lists for the hooks called one by one; records go through
        # _record_hooks, which keeps each listener's batch-or-single choice
        self._by_hook: dict[str, list[tuple[_Slot, Callable[..., Any]]]] = {h: [] for h in _INDEXED}
        self._record_hooks: list[tuple[_Slot, Any, Any]] = []
        self._stderr = stderr
        self._clock = clock
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        #: the run's stream ids: every source takes its own here (no two collide)
        self.stream_ids = StreamIds()
        self._tickers: list[Ticking] = []
        self._closed = False
        self._finished = False
        self.now = 0.0  # the run's time: the newest input timestamp, or the clock when live
        self._next_listener_tick = 0.0
        #: messages of source errors (ERROR events without a stream: damaged input)
        self.errors: list[str] = []
        #: ``(listener name, message)`` of every listener detached after an error
        self.failures: list[tuple[str, str]] = []
        self.records = 0
        #: chunks and events fed so far (read from other threads: a live source's
        #: measure of how far behind the hub is, e.g. the proxy's observer)
        self.seen = 0
        #: no more input is wanted: every listener is gone, or -c N was reached
        self.done = False
        for listener in listeners:
            self.add_listener(listener)

    # ------------------------------------------------------------------ wiring

    def add_listener(self, listener: Any) -> None:
        """Attach ``listener``; its hooks are looked up now and called only where defined."""
        self._slots.append(_Slot(listener, listener_name(listener), hooks_of(listener)))
        self._index_hooks()

    def add_ticker(self, stage: Ticking) -> None:
        """A stage before the pipeline (a dissector) that needs ``tick(now)`` and says when."""
        self._tickers.append(stage)

    @property
    def listeners(self) -> list[Any]:
        """The listeners still attached, in the order they were added."""
        return [slot.listener for slot in self._slots]

    def clock(self) -> float:
        """The run's wall clock (``time.time`` unless a test gave another)."""
        return self._clock()

    def new_stream(self, transport: Transport, client: str, server: str) -> Stream:
        """A stream with an id no other source of this run has (thread-safe)."""
        return Stream(self.new_stream_id(), transport, client, server)

    def new_stream_id(self) -> int:
        """The next stream id of the run (thread-safe), for sources that build their own."""
        return self.stream_ids.new()

    def recorded_streams(self) -> RecordedStreams:
        """For a source whose items carry stream ids of their own (a log's recorded
        ones): the map that puts them on the run's ids, one per source."""
        return RecordedStreams(self.stream_ids)

    def _index_hooks(self) -> None:
        by_hook: dict[str, list[tuple[_Slot, Callable[..., Any]]]] = {h: [] for h in _INDEXED}
        for slot in self._slots:
            for hook in _INDEXED:
                fn = getattr(slot.hooks, hook)
                if fn is not None:
                    by_hook[hook].append((slot, fn))
        self._by_hook = by_hook
        self._record_hooks = [
            (slot, slot.hooks.on_records, slot.hooks.on_record)
            for slot in self._slots
            if slot.hooks.takes_records
        ]

    # ------------------------------------------------------------------ same-thread input

    def feed(self, item: Item) -> None:
        """Take one chunk or event now, in the calling thread: :meth:`feed_items` of one."""
        self.feed_items((item,))

    def run_items(self, items: Iterable[Item]) -> None:
        """Feed every item of ``items`` (a file's), then finish the pipeline."""
        self.feed_items(items)
        self.finish()

    def feed_items(self, items: Iterable[Item]) -> None:
        """Feed every item of ``items`` in the calling thread, stopping early once
        :attr:`done` (every listener gone, or ``-c N`` reached).

        The one way input goes in (:meth:`feed` is this with one item): the run's
        time moves to the item's, the listeners get it as the source gave it, then
        the pipeline, whose records are fanned out. A listener detached on the way
        is reported at the time of the item it failed on.
        """
        chunk_hooks = self._by_hook["on_chunk"]
        event_hooks = self._by_hook["on_event"]
        pipeline_feed = self.pipeline.feed
        dispatch = self._dispatch
        error = EventKind.ERROR
        n = 0
        for item in items:
            n += 1
            ts = item.ts
            if ts > self.now:
                self.now = ts
            if isinstance(item, Chunk):
                if chunk_hooks:
                    for slot, fn in chunk_hooks:
                        self._call(slot, fn, item)
                    chunk_hooks = self._by_hook["on_chunk"]
            else:
                if item.kind is error and item.stream is None:
                    self.errors.append(str(item.info.get("message", "damaged input")))
                if event_hooks:
                    for slot, fn in event_hooks:
                        self._call(slot, fn, item)
                    event_hooks = self._by_hook["on_event"]
            records = pipeline_feed(item)
            if records:
                dispatch(records)
                if self.done:
                    break  # every listener is gone (stdout closed, nothing recorded)
        self.seen += n

    def iter_records(self, items: Iterable[Item]) -> Iterator[Record]:
        """Feed ``items`` (then finish) and yield every record as it is made, in order,
        after the listeners had it: for a caller that consumes records itself
        (``replay --redecode`` filters and paces them)."""
        made: list[Record] = []
        collector = _Collector(made)
        self.add_listener(collector)
        try:
            for item in items:
                self.feed(item)
                if made:
                    yield from made
                    made.clear()
            self.finish()
            yield from made
            made.clear()
        finally:
            if collector in self.listeners:
                self._slots = [s for s in self._slots if s.listener is not collector]
                self._index_hooks()

    def tick(self, now: float | None = None) -> None:
        """Move the run's time to ``now`` (default: the clock): stages, pipeline, listeners."""
        if now is None:
            now = self._clock()
        if now > self.now:
            self.now = now
        for stage in self._tickers:
            for item in stage.tick(now):
                self.feed(item)
        records = self.pipeline.tick(now)
        if records:
            self._dispatch(records)
        for slot, fn in self._by_hook["on_tick"]:
            self._call(slot, fn, now)

    def next_deadline(self) -> float | None:
        """The earliest time a stage or the pipeline needs a tick, or ``None``."""
        deadlines = [self.pipeline.next_deadline()]
        deadlines.extend(stage.next_deadline() for stage in self._tickers)
        known = [d for d in deadlines if d is not None]
        return min(known) if known else None

    def finish(self) -> None:
        """End of input: the stages and the pipeline report what they still hold."""
        if self._finished:
            return
        self._finished = True
        self._finish_input()

    def end_of_input(self) -> None:
        """One source's input ended and another source's follows (file and stream
        sources are read one after another): the stages and the pipeline report what
        the first still holds, and the run's time starts again with the next one's,
        so each input is decoded as it is alone (its requests time out at its own
        end, its time never holds back the next one's ticks)."""
        self._finish_input()
        self.now = 0.0

    def _finish_input(self) -> None:
        for stage in self._tickers:
            finish = getattr(stage, "finish", None)
            if callable(finish):
                for item in finish(self.now):
                    self.feed(item)
        records = self.pipeline.finish()
        if records:
            self._dispatch(records)

    # ------------------------------------------------------------------ thread-safe input

    def put(self, item: Item) -> None:
        """Queue a chunk or event from any thread; :meth:`run` feeds it in the hub's thread."""
        self._queue.put(item)

    def submit(self, producer: Producer) -> None:
        """Queue ``producer`` from any thread: it runs in the hub's thread, and the
        chunks and events it returns are fed (a dissector's ``packet`` call)."""
        self._queue.put(producer)

    def stop(self) -> None:
        """Ask :meth:`run` to finish what is queued and return (any thread, signal handlers)."""
        self._queue.put(_STOP)

    def run(
        self,
        stop: threading.Event | None = None,
        *,
        until_idle: bool = False,
        on_stop: Callable[[], object] | None = None,
    ) -> None:
        """The live loop: feed queued input, tick on the deadlines, until :meth:`stop`.

        Sleeps until the next deadline of any stage (at most ``MAX_SLEEP``), so an
        unanswered request is reported at its timeout while the line is silent, and
        listeners' ``on_tick`` runs every ``LISTENER_TICK`` seconds. ``until_idle``
        returns as soon as the queue is empty (tests). On the way out, ``on_stop``
        (the sources stop delivering; it may block) runs in this thread, then what
        is queued is fed, so nothing a source delivered before it stopped is lost;
        then the pipeline finishes. :meth:`close` is the caller's.
        """
        get = self._queue.get
        get_nowait = self._queue.get_nowait
        next_check = 0.0
        while stop is None or not stop.is_set():
            wait = self._sleep_time()
            if wait <= 0:  # a deadline is due: wait no longer than the next look at it
                wait = max(0.0, next_check - self._clock())
            try:
                item = get(timeout=wait) if wait > 0 else get_nowait()
            except queue.Empty:
                item = None
                if until_idle:
                    break
            if item is _STOP:
                break
            if item is not None:
                # take what else is queued (up to a batch) before looking at the clock:
                # deadlines are looked at per batch, not per packet
                self._take(item)
                for _ in range(BATCH):
                    try:
                        item = get_nowait()
                    except queue.Empty:
                        break
                    if item is _STOP:
                        self._end(on_stop)
                        return
                    self._take(item)
            now = self._clock()
            if now < next_check:
                continue
            next_check = now + CHECK_EVERY
            deadline = self.next_deadline()
            if (deadline is not None and now >= deadline) or now >= self._next_listener_tick:
                self._next_listener_tick = now + LISTENER_TICK
                self.tick(now)
        self._end(on_stop)

    def _end(self, on_stop: Callable[[], object] | None) -> None:
        """The end of :meth:`run`: the sources stop, what they queued is fed, finish."""
        if on_stop is not None:
            try:
                on_stop()
            except Exception as exc:  # a source's own bug must not lose what is queued
                self._notice(f"source failed to stop: {type(exc).__name__}: {exc}")
        self._drain()
        self.finish()

    def _take(self, item: Any) -> None:
        if isinstance(item, (Chunk, Event)):
            self.feed(item)
            return
        try:
            produced = item()
        except Exception as exc:  # a source's own bug must not end the run
            self._notice(f"source failed: {type(exc).__name__}: {exc}")
            return
        if produced:
            self.feed_items(produced)  # a batch: the proxy's, the sniffer's

    def _drain(self) -> None:
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if item is not _STOP:
                self._take(item)

    def _sleep_time(self) -> float:
        now = self._clock()
        wake = self._next_listener_tick
        deadline = self.next_deadline()
        if deadline is not None and deadline < wake:
            wake = deadline
        return max(0.0, min(MAX_SLEEP, wake - now))

    # ------------------------------------------------------------------ fan-out and isolation

    def enough(self) -> None:
        """No more input is wanted (``-c N`` reached): :meth:`run_items` and :meth:`run`
        stop taking input, and the pipeline finishes as at the end of the input."""
        self.done = True
        self._queue.put(_STOP)

    def _dispatch(self, records: list[Record]) -> None:
        """Each listener gets the batch in the order listeners were added (a log added
        before the console has every record the console printed, whenever a signal
        comes): the batch hook at once, or ``on_record`` per record."""
        self.records += len(records)
        for slot, batch, each in self._record_hooks:
            try:
                if batch is not None:
                    batch(records)
                else:
                    for record in records:
                        each(record)
            except Exception as exc:
                self._detach(slot, exc)

    def _call(self, slot: _Slot, fn: Callable[..., Any], arg: Any) -> None:
        try:
            fn(arg)
        except Exception as exc:
            self._detach(slot, exc)

    def _detach(self, slot: _Slot, exc: BaseException) -> None:
        """Report a failed listener once, close it, and go on without it."""
        if slot not in self._slots:
            return
        self._slots.remove(slot)
        self._index_hooks()
        self.done = not self._slots
        if isinstance(exc, BrokenPipeError):
            _quiet_stdout()  # the reader went away (| head): nothing to report
            self.failures.append((slot.name, "broken pipe"))
            return
        message = _describe(exc)
        self.failures.append((slot.name, message))
        text = f"{slot.name} stopped: {message}" if slot.name not in message else message
        self._say(f"mbmon: {text}; the rest of the run goes on")
        close = slot.hooks.close
        if close is not None:
            try:
                close()
            except Exception:
                pass
        self._notice(f"{text}; detached")

    def _notice(self, message: str) -> None:
        """A NOTICE event about the run itself, shown to the listeners still attached."""
        event = Event(self.now, None, EventKind.NOTICE, {"message": message})
        records = self.pipeline.feed(event)
        if records:
            self._dispatch(records)

    def _say(self, text: str) -> None:
        out = self._stderr if self._stderr is not None else sys.stderr
        try:
            print(text, file=out, flush=True)
        except (OSError, ValueError):
            pass

    # ------------------------------------------------------------------ end

    def close(self) -> None:
        """Close every listener, in the order they were added; each close runs whatever
        the others do. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for slot in list(self._slots):
            close = slot.hooks.close
            if close is None:
                continue
            try:
                close()
            except Exception as exc:
                self._slots.remove(slot)
                if isinstance(exc, BrokenPipeError):
                    _quiet_stdout()
                    continue
                message = _describe(exc)
                self.failures.append((slot.name, message))
                self._say(f"mbmon: {message}")

    def __enter__(self) -> Hub:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _describe(exc: BaseException) -> str:
    """One line for a listener's failure: the file and the OS's words when there are some."""
    if isinstance(exc, OSError) and exc.strerror:
        where = f"{exc.filename}: " if exc.filename else ""
        return f"{where}{exc.strerror}"
    text = str(exc)
    return text if text else type(exc).__name__


def _quiet_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's last flush cannot fail again."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass
