"""The core on a source of byte chunks (the proxy's observation): chunks and the
source's events in, lines out, the reference pipeline taking over the whole run at
the first thing the core does not cover.

:class:`ChunkCore` is a hub stage (``tick``, ``next_deadline``, ``finish``) and the
function the proxy's pipe reader hands its reads to, in the hub's thread
(:meth:`ChunkCore.take`): runs of chunk records go into the core's chunk entry
(:class:`mbmon.core._reader._Chunks`, ``pipe``: no Python object per chunk), the
pipe's streams and events one by one. While the core covers the traffic it writes
the lines itself (``write``: the console's bytes) and gives the hub nothing to feed;
from the first chunk, event, tick or end it does not cover, it hands its state to
the hub's pipeline (``export_to``) and from then on turns the pipe's records into
the chunks and events the hub feeds. What it covers is in docs/architecture.md
("The core on the proxy's observation").
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import mbmon.core as _core
from mbmon.core import _load
from mbmon.model import Event, EventKind, Stream

__all__ = ["ChunkCore", "decline_for_proxy"]

#: a read of the proxy's pipe, cut for the hub's thread: runs of chunk records
#: (bytes), ``("stream", key, Stream)`` and the child's event records
#: ``("event", ts, key, kind, info)``, in order
Segment = bytes | tuple[Any, ...]


def decline_for_proxy(args: Any, *, process: bool, console: bool) -> str | None:
    """Why ``proxy``'s options keep its observation off the core (the reference
    pipeline observes from the start), or ``None``: a TCP proxy (its forwarding in a
    child process) printing lines or ``--json`` to stdout, or ``-q``, with at most one
    ``-w x.mcap`` log, nothing else."""
    write = list(getattr(args, "write", None) or [])
    checks = (
        (not process, "a serial side (the engine in a thread)"),
        (not console and not getattr(args, "quiet", False), "the live screen"),
        (len(write) > 1, "several -w logs"),
        (write and not str(write[0]).lower().endswith(".mcap"), "-w other than one .mcap log"),
        (getattr(args, "foxglove", None), "--foxglove"),
        (getattr(args, "trigger", None), "--trigger"),
        (getattr(args, "rotate", None), "--rotate"),
        (getattr(args, "profile", None), "--profile"),
    )
    return _core.first_decline(checks)


class ChunkCore:
    """The core as the stage between the proxy's pipe and the hub (see the module doc).

    ``pipeline`` is the hub's (empty until the hand-over); ``write(bytes)`` takes the
    core's output (UTF-8 lines), ``flush()`` after each batch; ``write=None`` (``-q``):
    the lines are made and dropped, as the reference makes records nobody prints."""

    def __init__(
        self,
        *,
        timeout: float,
        view: Any,
        as_json: bool,
        write: Callable[[bytes], Any] | None,
        flush: Callable[[], Any] | None = None,
        pipeline: Any,
    ) -> None:
        why = _load()
        if why is not None:
            raise RuntimeError(f"the compiled core is unavailable: {why}")
        reader: Any = _core._reader
        self._core: Any = reader._Chunks(as_json, timeout, view, write)
        self.scan: Callable[[Any, int], tuple[int, int, list[tuple[int, int]]]] = reader.pipe_scan
        self.pipeline = pipeline
        self._flush = flush
        #: the source's stream ids -> the hub's streams (a client's and its proxy
        #: answers' are forgotten at its DISCONNECT while the core observes)
        self.streams: dict[int, Stream] = {}
        self._own: dict[int, int] = {}  # a client stream's id -> its own answers' (source ids)
        #: why the run left the core (``None``: it did not)
        self.handed: str | None = None

    def log_to(self, sink: Any) -> None:
        """Write the run's ``-w x.mcap`` messages into ``sink`` (an open
        :class:`~mbmon.sinks.mcap.McapSink`, also the hub's listener for what the
        reference writes after a hand-over); before the hub's loop starts."""
        self._core.log_to(sink)

    @property
    def taken(self) -> int:
        """Pipe records (chunks and events) the core took: the hub never sees them
        (the pipe reader's backlog meter adds them to ``hub.seen``)."""
        n: int = self._core.taken
        return n

    # ------------------------------------------------------------------ input

    def take(self, segments: list[Segment]) -> list[Any]:
        """One read of the pipe, in the hub's thread: what the hub must feed (nothing
        while the core covers the traffic)."""
        out: list[Any] = []
        core = self._core
        try:
            for seg in segments:
                if self.handed is None:
                    if isinstance(seg, bytes):
                        pos = core.pipe(seg, 0, len(seg))
                        if pos == len(seg):
                            continue
                        self._hand_over()
                        seg = seg[pos:]
                    elif seg[0] == "stream":
                        self.streams[seg[1]] = seg[2]
                        core.add_stream(seg[1], seg[2])
                        continue
                    else:
                        event = self._event(seg)
                        if core.source_event(event.ts, event.stream, event.kind, event.info):
                            self._ended(seg, event)
                            continue
                        self._hand_over()
                        out.append(event)
                        continue
                self._reference(seg, out)
        finally:
            if self.handed is None:
                core.flush_log()
            if self._flush is not None:
                self._flush()
        return out

    def event(self, event: Event) -> list[Any]:
        """An event of the command's own (a warning), in the hub's thread."""
        if self.handed is None:
            taken = self._core.source_event(event.ts, event.stream, event.kind, event.info)
            if taken:
                self._core.flush_log()
            if self._flush is not None:
                self._flush()
            if taken:
                return []
            self._hand_over()
        return [event]

    def _ended(self, record: tuple[Any, ...], event: Event) -> None:
        """A client's CONNECT joins its own answers' stream; its DISCONNECT (taken by
        the core) ends both: their ids are forgotten (the engine sends nothing more
        on them)."""
        key = record[2]
        if event.kind is EventKind.CONNECT:
            own = record[4].get("answers_on")
            if type(own) is int:
                self._own[key] = own
        elif event.kind is EventKind.DISCONNECT:
            self.streams.pop(key, None)
            own = self._own.pop(key, None)
            if own is not None:
                self.streams.pop(own, None)

    def _event(self, record: tuple[Any, ...]) -> Event:
        _, ts, key, kind, info = record
        if "answers_on" in info:  # a stream id of the child's: the hub's instead
            info = {**info, "answers_on": self.streams[info["answers_on"]].id}
        return Event(ts, None if key < 0 else self.streams[key], EventKind(kind), info)

    def _reference(self, seg: Segment, out: list[Any]) -> None:
        """A segment after the hand-over: the chunks and events the hub feeds."""
        if isinstance(seg, bytes):
            from mbmon.proxy.remote import decode_records

            items, _others, _used = decode_records(bytearray(seg), self.streams, _no_stream)
            out.extend(items)
        elif seg[0] == "stream":
            self.streams[seg[1]] = seg[2]
        else:
            out.append(self._event(seg))

    # ------------------------------------------------------------------ the hub's stage

    def tick(self, now: float) -> Iterable[Any]:
        """The hub's tick (before its pipeline's): the core's; after the hand-over the
        pipeline's alone."""
        if self.handed is None:
            done = self._core.tick(now)
            if not done:
                self._core.flush_log()
            if self._flush is not None:
                self._flush()
            if done:
                self._hand_over()  # the hub ticks the pipeline next
        return []

    def next_deadline(self) -> float | None:
        """When the stage next needs a tick, or ``None``."""
        if self.handed is None:
            deadline: float | None = self._core.next_deadline()
            return deadline
        return None

    def finish(self, ts: float) -> list[Any]:
        """The end of input at the hub's time ``ts``."""
        if self.handed is None:
            finished = self._core.finish(ts)
            if finished:
                self._core.flush_log()
            if self._flush is not None:
                self._flush()
            if not finished:
                self._hand_over()
        return []

    def counts(self) -> dict[str, Any]:
        """What the core wrote, as ``read``'s summary counts it."""
        from mbmon.core import _counts

        return _counts(self._core)

    def _hand_over(self) -> None:
        self.handed = str(self._core.reason or "the end of what the core covers")
        self._core.flush_log()  # the log's sink goes on from the core's counters
        self._core.export_to(self.pipeline)


def _no_stream(*_args: Any) -> Stream:  # pragma: no cover - chunk runs carry no streams
    raise RuntimeError("a stream record in a run of chunk records")
