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

__all__ = ["LiveCore", "add_counts", "decline_for_sniff"]


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
        write: Callable[[bytes], Any],
        flush: Callable[[], Any] | None = None,
        new_stream: Callable[..., Any],
        dissector: Any,
        pipeline: Any,
    ) -> None:
        why = _load()
        if why is not None:
            raise RuntimeError(f"the compiled core is unavailable: {why}")
        reader: Any = _core._reader
        self._core: Any = reader._Live(
            as_json, timeout, ports, view, write, new_stream, keep_noise=True
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
