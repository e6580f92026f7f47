"""The core on a live capture: packet batches in, lines out, the reference pipeline
taking over the whole run at the first thing the core does not cover.

:class:`LiveCore` is a hub stage (``tick``, ``next_deadline``, ``finish``, like the
packet dissector it stands in for) and the function the capture thread's batches
run through in the hub's thread (:meth:`LiveCore.packets`). While the core covers
the traffic it writes the lines itself (through ``write``, the console's bytes)
and gives the hub nothing to feed; from the first packet, tick or end it does not
cover, it hands its state to the reference dissector and the hub's pipeline
(:meth:`mbmon.core._reader._Live.export`) and from then on is the reference
dissector (its chunks and events go through the hub and its listeners). The rule
and what the core covers are in docs/architecture.md ("The core on a live capture").
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import mbmon.core as _core
from mbmon.core import _load

__all__ = [
    "LiveCore",
    "PipeCore",
    "add_counts",
    "decline_for_pipe",
    "decline_for_sniff",
    "run_pipe",
]


def decline_for_sniff(args: Any, *, interface: bool, console: bool, flt: Any) -> str | None:
    """Why ``sniff``'s options keep the run off the core (the reference runs it from
    the start), or ``None``: a network interface, ``--port`` named (port detection
    off), lines or ``--json`` to stdout, nothing else."""
    checks = (
        (not interface, "--serial (RTU)"),
        (getattr(args, "rtu_port", None), "--rtu-port (RTU over TCP/UDP)"),
        (not (getattr(args, "port", None) or getattr(args, "no_detect", False)), "port detection"),
        (not console, "the live screen or -q"),
        (getattr(args, "write", None), "-w (logs)"),
        (getattr(args, "foxglove", None), "--foxglove"),
        (getattr(args, "trigger", None), "--trigger"),
        (getattr(args, "rotate", None), "--rotate"),
        (getattr(args, "profile", None), "--profile"),
        (getattr(args, "robot", None), "--robot"),
        (getattr(args, "count", None), "-c"),
        (flt is not None and getattr(flt, "active", False), "filters"),
        (getattr(args, "time_format", "a") != "a", "-t other than a"),
    )
    return _core.first_decline(checks)


class LiveCore:
    """The core as the stage between a live capture and the hub (see the module doc).

    ``dissector`` is the reference dissector of the run (fresh, its stream ids the
    hub's ``new_stream``) and ``pipeline`` the hub's: both stay empty until the
    hand-over. ``write(bytes)`` takes the core's output (UTF-8 lines)."""

    def __init__(
        self,
        *,
        ports: frozenset[int],
        timeout: float,
        view: Any,
        as_json: bool,
        write: Callable[[bytes], Any] | None,
        flush: Callable[[], Any] | None = None,
        new_stream: Callable[..., Any],
        dissector: Any,
        pipeline: Any,
        detect: bool = False,
        file_mode: bool = False,
    ) -> None:
        why = _load()
        if why is not None:
            raise RuntimeError(f"the compiled core is unavailable: {why}")
        reader: Any = _core._reader
        self._core: Any = reader._Live(
            as_json,
            timeout,
            ports,
            view,
            write,
            new_stream,
            keep_noise=True,
            detect=detect,
            file_mode=file_mode,
        )
        self.dissector = dissector
        self.pipeline = pipeline
        self._flush = flush
        #: why the run left the core (``None``: it did not)
        self.handed: str | None = None

    # ------------------------------------------------------------------ input

    def packets(self, batch: list[tuple[float, int, bytes]]) -> list[Any]:
        """One batch of captured packets, in the hub's thread: what the hub must feed
        (nothing while the core covers the traffic)."""
        if self.handed is None:
            taken = self._core.feed(batch)
            if self._flush is not None:
                self._flush()
            if taken == len(batch):
                return []
            self._hand_over()
            batch = batch[taken:]
        out: list[Any] = []
        packet_bytes = self.dissector.packet_bytes
        for ts, linktype, data in batch:
            out.extend(packet_bytes(ts, linktype, data))
        return out

    # ------------------------------------------------------------------ the hub's stage

    def tick(self, now: float) -> Iterable[Any]:
        """The hub's tick (before its pipeline's): the core's, or the reference's."""
        if self.handed is None:
            done = self._core.tick(now)
            if self._flush is not None:
                self._flush()
            if done == 0:
                return []
            self._hand_over()
            if done == 2:  # the core did the dissector's part; the pipeline does the rest
                return []
        return self.dissector.tick(now)

    def next_deadline(self) -> float | None:
        """When the stage next needs a tick, or ``None``."""
        if self.handed is None:
            deadline: float | None = self._core.next_deadline()
            return deadline
        got: float | None = self.dissector.next_deadline()
        return got

    def finish(self, ts: float) -> list[Any]:
        """The end of input at the hub's time ``ts``."""
        if self.handed is None:
            finished = self._core.finish(ts)
            if self._flush is not None:
                self._flush()
            if finished:
                # what the hub feeds after the end (the source's closing events) is
                # the pipeline's to number: from the core's record numbers on
                self.pipeline._index = self._core.index
                return []
            self._hand_over()
        got: list[Any] = self.dissector.finish(ts)
        return got

    def counts(self) -> dict[str, Any]:
        """What the core wrote, as ``read``'s summary counts it (add them with
        :func:`add_counts`; the reference's records after a hand-over are the
        summary listener's own)."""
        from mbmon.core import _counts

        return _counts(self._core)

    def stats(self) -> dict[str, int]:
        """The dissector's figures, the core's part included."""
        stats: dict[str, int] = dict(self.dissector.stats())
        if self.handed is None:
            stats["modbus_packets"] = stats.get("modbus_packets", 0) + self._core.modbus_packets
            stats["open_connections"] = self._core.open_connections()
            stats["streams"] = self._core.streams_made()
        return stats

    def detected(self) -> list[tuple[str, int, str, int]]:
        """Port detection is off on the core: what the reference found after a hand-over."""
        got: list[tuple[str, int, str, int]] = self.dissector.detected()
        return got

    def _hand_over(self) -> None:
        self.handed = str(self._core.reason or "the end of what the core covers")
        self._core.export(self.dissector, self.pipeline)


def add_counts(summary: Any, counts: dict[str, Any]) -> None:
    """Add the core's counts to a :class:`~mbmon.sinks.summary.Summary` that also
    counted the reference's records (after a hand-over)."""
    for name in ("requests", "responses", "exceptions", "timeouts", "unsolicited", "malformed"):
        setattr(summary, name, getattr(summary, name) + counts[name])
    summary.max_stream = max(summary.max_stream, counts["max_stream"])
    for name, pick in (("first", min), ("last", max)):
        mine = counts[name]
        if mine is not None:
            theirs = getattr(summary, name)
            setattr(summary, name, mine if theirs is None else pick(theirs, mine))
    for name, n in counts["events"].items():
        summary.events[name] = summary.events.get(name, 0) + n
    summary.noise_records += counts.get("noise_records", 0)  # MBAP noise the core reported
    summary.noise_bytes += counts.get("noise_bytes", 0)


# ------------------------------------------------------------------ read from a pipe

#: records the pipe's reader hands the hub's thread at once (at most)
PIPE_RECORDS = 4096
#: blocks of a classic pcap's bytes read ahead of the core (at most)
PIPE_BLOCKS = 32


def decline_for_pipe(args: Any, *, flt: Any, annotator: Any) -> str | None:
    """Why ``read``'s options keep a capture on a pipe, FIFO or stdin off the core's
    streaming entry (the reference reads it from the start), or ``None``: what
    :func:`mbmon.core.decline_for_options` declines for a file, and what the
    streaming entry does not cover yet (``-w``, ``--profile``, ``--since``/``--until``
    or ``--grep`` with ``-c``, whose start a file's deciding pass finds)."""
    active = flt is not None and getattr(flt, "active", False)
    checks = (
        (args.write, "-w (logs) from a pipe"),
        (annotator is not None or args.profile, "--profile from a pipe"),
        # with -c, resolved at the first frame of the first batch -c's budget is asked
        # about (a file's deciding pass finds it; without -c the core resolves them at
        # the first record, as the console's filter does)
        (
            active and (args.since or args.until) and args.count,
            "--since/--until with -c from a pipe",
        ),
        (active and args.grep and args.count, "--grep with -c from a pipe"),
    )
    return _core.decline_for_options(args, live=False, flt=flt) or _core.first_decline(checks)


class PipeCore(LiveCore):
    """The core as ``read``'s stage between a capture on a pipe and the hub: the
    streaming entry with the file dissector's rules (``_Live(file_mode=True)``: no
    idle expiry, no hole timeout, the dissector never ticked) and port detection,
    handing the whole run to ``dissector`` (a file's :class:`~mbmon.sources.dissect.Dissector`)
    and the hub's pipeline at the first record, tick or end it does not cover, as
    :class:`LiveCore` does for ``sniff``. Records are ``(ts, link type, bytes,
    interface)``."""

    def __init__(
        self,
        *,
        ports: frozenset[int],
        timeout: float,
        view: Any,
        as_json: bool,
        write: Callable[[bytes], Any] | None,
        flush: Callable[[], Any] | None = None,
        new_stream: Callable[..., Any],
        dissector: Any,
        pipeline: Any,
        detect: bool,
        flt: Any = None,
        count: int | None = None,
        budget: Any = None,
    ) -> None:
        super().__init__(
            ports=ports,
            timeout=timeout,
            view=view,
            as_json=as_json,
            write=write,
            flush=flush,
            new_stream=new_stream,
            dissector=dissector,
            pipeline=pipeline,
            detect=detect,
            file_mode=True,
        )
        # the reference dissector judges other ports with the very detector the core feeds
        detector = self._core.port_detector()
        if detector is not None:
            dissector.detector = detector
        # the other ports' counts (the summary's hint) go on in the dissector's own dict
        self._core.port_counts = dissector._ports
        if flt is not None and not flt.active:
            flt = None
        if flt is not None or count is not None:  # the console behind the filters, -c
            self._core.select(flt, count, write is not None)
        #: ``-c``'s budget of the reference's wiring (its count is the core's at a hand-over)
        self.budget = budget
        #: ``-c``'s last frame was written: the run ends there
        self.enough = False
        # a classic pcap parsed by the core (``pcap``): its parameters, the bytes of a
        # record not whole yet and their offset, and a corrupt record header (what, offset)
        self._pcap: tuple[bool, float, int, int, int] | None = None
        self.buf = b""
        self.base = 0
        self.damage: tuple[str, int] | None = None

    def now(self, hub_now: float) -> float:
        """The hub's time as the reference's would be: the newest item's."""
        if self.handed is None:
            latest: float = self._core.item_ts
            return latest if latest > hub_now else hub_now
        return hub_now

    def packets(self, batch: list[Any]) -> list[Any]:
        """One batch of records, in the hub's thread: what the hub must feed."""
        out: list[Any] = []
        if self.handed is None:
            try:
                taken = self._core.feed(batch)
            except _core._reader.Enough:
                self.enough = True
                return out
            if self._flush is not None:
                self._flush()
            if taken == len(batch):
                return out
            promotion = self._core.promotion
            self._hand_over()
            if promotion is not None:  # the detector took that record: its replay
                self.dissector._promote(promotion, out)
                taken += 1
            batch = batch[taken:]
        packet = self.dissector.packet
        for ts, linktype, data, iface in batch:
            packet(ts, linktype, iface, data, 0, len(data), out)
        return out

    def pcap(self, endian: str, divisor: float, link: int, snaplen: int, header: int) -> None:
        """The capture is a classic pcap (the pump's parameters): its records are parsed
        by the core from the pipe's bytes (:meth:`block`), not by the pump."""
        from mbmon.sources.pcapfile import _MAX_RECORD

        self._pcap = (endian == ">", divisor, header, link, min(max(snaplen, 262144), _MAX_RECORD))

    def block(self, data: bytes) -> list[Any]:
        """Bytes of a classic pcap as the pipe gave them (after its file header, in
        order), in the hub's thread: what the hub must feed. Records left whole wait
        for the next bytes; a corrupt record header ends the records (``damage``)."""
        buf = self.buf + data if self.buf else data
        pos = 0
        out: list[Any] = []
        records = self._core.pcap_records
        assert self._pcap is not None
        big, divisor, header, link, limit = self._pcap
        if self.handed is None:
            try:
                pos = records(buf, pos, big, divisor, header, link, limit)
            except _core._reader.Enough:
                self.enough = True
                return out
            if self._core.rec_stop == 1:  # the run goes to the reference from here
                promotion = self._core.promotion
                self._hand_over()
                if promotion is not None:  # the detector took that record: its replay
                    self.dissector._promote(promotion, out)
        if self.handed is not None and self._core.rec_stop != 2:
            taken: list[Any] = []
            pos = records(buf, pos, big, divisor, header, link, limit, taken)
            out.extend(self.packets(taken))
        if self._core.rec_stop == 2:
            self.damage = (f"corrupt record header (length {self._core.rec_len})", self.base + pos)
        self.buf = buf[pos:]
        self.base += pos
        return out

    def block_end(self, failure: BaseException | None) -> tuple[float, BaseException | None]:
        """Where the records of a pcap read by :meth:`block` ended: the end's time and
        what ended them early (``failure``, the reader's; or damage: a corrupt header,
        or a record the pipe cut), as the pump's ``_Damage``."""
        from mbmon.sources.pcapfile import _Damage

        assert self._pcap is not None
        if self.damage is not None:
            failure = _Damage(*self.damage)
        elif failure is None and self.buf:
            header = self._pcap[2]
            what = "truncated record header" if len(self.buf) < header else "truncated record"
            failure = _Damage(what, self.base)
        if not isinstance(failure, _Damage):
            return self._core.rec_ts, failure
        return self.good_ts(self._core.rec_ts), failure

    def good_ts(self, fallback: float) -> float:
        """The time of the last record that parsed as a packet (``Dissector.good_ts``:
        the end of a damaged capture): the reference dissector's after a hand-over (it
        read the later records), else the core's; ``fallback`` when none did."""
        good: float | None = self.dissector.good_ts
        if good is not None:
            return good
        mine: float = self._core.good_ts
        return fallback if mine != mine else mine  # NaN: none

    def tick(self, now: float) -> Iterable[Any]:
        """The hub's tick at ``now``, the core's part (the pipeline's, as a file's
        dissector is never ticked); the hub's own tick follows."""
        if self.handed is None:
            try:
                done = self._core.tick(now)
            except _core._reader.Enough:  # a frame settled after a silence was the last
                self.enough = True
                return []
            if self._flush is not None:
                self._flush()
            if done != 0:  # nothing of the tick done: the hub's pipeline does it
                self._hand_over()
        return []

    def _hand_over(self) -> None:
        super()._hand_over()
        if self.budget is not None:
            self.budget.left = self._core.frames_left()

    def end(self, ts: float, error: str | None) -> list[Any]:
        """The end of the records at ``ts`` (the last record's time), ``error`` the
        ERROR event's words when they ended early: the dissector's end and that
        event, as the hub must feed them (nothing when the core did it all: the
        hub's ``finish`` then finds the pipeline empty)."""
        from mbmon.model import Event, EventKind

        if self.handed is None:
            finished = False
            if error is None:
                try:
                    finished = self._core.finish(ts)
                except _core._reader.Enough:  # -c's last frame came with the end
                    self.enough = finished = True
            if finished:
                if self._flush is not None:
                    self._flush()
                self.pipeline._index = self._core.index
                return []
            if error is not None:
                self._core.reason = "the capture ended early"
            self._hand_over()
        out: list[Any] = self.dissector.finish(ts)
        if error is not None:
            out.append(Event(ts, None, EventKind.ERROR, {"message": error}))
        return out

    def stats(self) -> dict[str, Any]:
        """What ``read``'s summary asks of the capture: the ports found by their
        structure and the busiest other ports (the reference dissector's)."""
        return {
            "detected": self.dissector.detected(),
            "busiest_ports": self.dissector.busiest_ports(),
        }


class _End:
    """The pipe reader's last word: ``failure`` ended the records early (damage or a
    read error), ``error`` is an exception of the reader itself (raised again)."""

    def __init__(self, failure: BaseException | None = None, error: BaseException | None = None):
        self.failure = failure
        self.error = error


class _Flushing:
    """The capture's file as its input reads it (``read1``), handing the records
    parsed so far to the hub's thread before every read that may wait."""

    def __init__(self, f: Any, flush: Callable[[], None]) -> None:
        self._f = f
        self._flush = flush

    def read1(self, n: int) -> bytes:
        self._flush()
        read = getattr(self._f, "read1", self._f.read)
        data: bytes = read(n)
        return data

    read = read1


class _PipeReader:
    """The reader thread of :func:`run_pipe`: the capture's records parsed as they
    come, handed to the hub's thread in lists (``inbox``), the last an :class:`_End`."""

    def __init__(self, opened: tuple[Any, Any, Any]) -> None:
        import queue

        self.inp, self.pump, self.raw = opened
        self.inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.pending: list[Any] = []
        self.inp.f = _Flushing(self.inp.f, self.flush)

    def flush(self) -> None:
        """The records parsed so far to the hub's thread (before a read may wait)."""
        if self.pending:
            self.inbox.put(self.pending[:])
            self.pending.clear()

    def packet(
        self, ts: float, link: int, iface: int, buf: bytes, start: int, stop: int, _: Any
    ) -> None:
        """The pump's ``packet``: one record kept (nothing appended to the pump's list)."""
        self.pending.append((ts, link, buf[start:stop], iface))
        if len(self.pending) >= PIPE_RECORDS:
            self.flush()

    def run(self) -> None:
        """Every record, then the end (with what ended the records early, if anything)."""
        from mbmon.sources.pcapfile import READ_FAILURES

        end = _End()
        try:
            for _ in self.pump(self.packet, []):  # ``packet`` appends nothing: no yield
                pass
        except READ_FAILURES as exc:
            end = _End(failure=exc)
        except BaseException as exc:  # handed to the hub's thread, raised there
            end = _End(error=exc)
        finally:
            self.raw.close()
        self.flush()
        self.inbox.put(end)


class _BlockReader:
    """The reader thread of :func:`run_pipe` for a classic pcap: the pipe's bytes as
    they come (what the input read past the file header first), the records parsed by
    the core in the hub's thread (:meth:`PipeCore.block`); the last an :class:`_End`."""

    def __init__(self, opened: tuple[Any, Any, Any]) -> None:
        import queue

        self.inp, _, self.raw = opened
        # bounded: a pipe faster than the core waits in the pipe, not in memory
        self.inbox: queue.Queue[Any] = queue.Queue(maxsize=PIPE_BLOCKS)

    def run(self) -> None:
        """Every block the pipe gives (up to the input's block size), then the end."""
        from mbmon.sources.pcapfile import _BLOCK, READ_FAILURES

        end = _End()
        inp = self.inp
        done = inp.base + len(inp.buf)  # bytes read so far (the progress bar's)
        try:
            if inp.pos < len(inp.buf):
                self.inbox.put(inp.buf[inp.pos :])
            read = getattr(inp.f, "read1", inp.f.read)
            while data := read(_BLOCK):
                self.inbox.put(data)
                done += len(data)
                if inp.progress is not None:
                    inp.progress(done, 0)  # a pipe: no size
        except READ_FAILURES as exc:
            end = _End(failure=exc)
        except BaseException as exc:  # handed to the hub's thread, raised there
            end = _End(error=exc)
        finally:
            self.raw.close()
        self.inbox.put(end)


def run_pipe(stage: PipeCore, hub: Any, opened: tuple[Any, Any, Any], name: str) -> None:
    """Read a capture arriving through a pipe (``opened``: what
    :func:`mbmon.sources.pcapfile.open_records` gave) through ``stage`` into ``hub``,
    as the reference's :func:`mbmon.sources.pipe.feed_pipe` reads its items: records
    parsed in a reader thread, taken in the hub's thread, the hub ticked every
    quarter second of wall time at the capture's time (never the clock's) whether
    records come or not; then the end (an ERROR event when the records ended early),
    and the hub finished. An exception of the reader, or a ``KeyboardInterrupt``
    while this waits, is raised here."""
    import queue
    import threading
    import time

    from mbmon.hub import BATCH, LISTENER_TICK
    from mbmon.sources.pcapfile import _pcap_pump

    pump = opened[1]
    reader: _PipeReader | _BlockReader
    if getattr(pump, "func", None) is _pcap_pump:  # a classic pcap: the core parses it
        inp, endian, divisor, link, snaplen, header = pump.args
        stage.pcap(endian, divisor, link, snaplen, header)
        stage.base = inp.base + inp.pos
        reader = _BlockReader(opened)
    else:
        reader = _PipeReader(opened)
    inbox = reader.inbox
    threading.Thread(target=reader.run, name="mbmon-pipe-reader", daemon=True).start()
    end: _End | None = None
    next_tick = time.monotonic() + LISTENER_TICK
    while end is None and not hub.done and not stage.enough:
        try:
            first = inbox.get(timeout=max(0.0, next_tick - time.monotonic()))
        except queue.Empty:
            first = None
        if first is None or time.monotonic() >= next_tick:
            next_tick = time.monotonic() + LISTENER_TICK
            now = stage.now(hub.now)
            stage.tick(now)
            hub.tick(now)  # the pipeline (after a hand-over) and the listeners
        if first is None:
            continue
        item, taken = first, 0
        while not isinstance(item, _End):
            if isinstance(item, bytes):
                items = stage.block(item)
                taken += BATCH  # a block of records: the clock is looked at after it
            else:
                items = stage.packets(item)
                taken += len(item)
            if items:
                hub.feed_items(items)
            if stage.damage is not None:  # a corrupt record header: the records end
                end = _End()
                break
            if taken >= BATCH or hub.done or stage.enough:
                break
            try:
                item = inbox.get_nowait()
            except queue.Empty:
                break
        else:
            end = item
    if stage.enough:  # -c: nothing after its last frame is written or counted
        return
    if end is not None:
        _end_pipe(stage, hub, end, reader.inp, name)
    hub.finish()


def _end_pipe(stage: PipeCore, hub: Any, end: _End, inp: Any, name: str) -> None:
    """The end of the pipe's records: the reader's own exception raised again, or the
    dissector's end (and the ERROR event of records that ended early) fed."""
    from mbmon.sources.pcapfile import _Damage, failure_message

    if end.error is not None:
        raise end.error
    error = None
    end_ts, failure = inp.last_ts, end.failure
    if stage._pcap is not None:  # the core parsed the records: its count and time
        end_ts, failure = stage.block_end(failure)
        inp.count, inp.last_ts = stage._core.rec_count, stage._core.rec_ts
    elif isinstance(failure, _Damage):  # the last records may be the damage itself
        end_ts = stage.good_ts(inp.last_ts)
    if failure is not None:
        error = failure_message(name, inp, failure)
    items = stage.end(end_ts, error)
    if items:
        hub.feed_items(items)
