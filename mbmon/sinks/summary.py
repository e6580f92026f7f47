"""The end-of-run summary: what a run saw, counted from its records, for stderr.

A listener like any other (``read``, ``sniff``, ``proxy`` and ``demo`` attach
it unless ``-q``): it counts frames, transactions, exceptions, timeouts, noise
and CRC errors, commands and their outcomes, streams and the time span, and
:meth:`Summary.text` renders them as the few lines a user reads after a run.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from mbmon.model import EventKind, Record, RecordKind
from mbmon.timefmt import human_span

_REQUEST, _RESPONSE, _EXCEPTION = RecordKind.REQUEST, RecordKind.RESPONSE, RecordKind.EXCEPTION
_NOISE, _EVENT, _COMMAND = RecordKind.NOISE, RecordKind.EVENT, RecordKind.COMMAND


class Summary:
    """Counts of one run's records; :meth:`text` is the summary shown at its end."""

    name = "summary"

    def __init__(self, view: Any = None) -> None:
        self.view = view
        #: the robot named by the view's ``--robot`` was on some stream
        self.robot_seen = False
        self.requests = 0
        self.responses = 0
        self.exceptions = 0
        self.timeouts = 0
        self.unsolicited = 0
        self.malformed = 0
        self.noise_records = 0
        self.noise_bytes = 0
        self.crc_errors = 0
        self.commands: Counter[str] = Counter()
        self.events: Counter[str] = Counter()
        self.max_stream = -1  # stream ids are allocated in order: the count is max + 1
        self.first: float | None = None
        self.last: float | None = None
        #: extra lines a source adds (kernel drops, bus health, proxy counters)
        self.extra: dict[str, Any] = {}

    @property
    def streams(self) -> int:
        """How many streams the run had (ids are given out in order from 0)."""
        return self.max_stream + 1

    def on_records(self, records: list[Record]) -> None:
        for record in records:
            kind = record.kind
            if kind is _REQUEST:
                self.requests += 1
            elif kind is _RESPONSE:
                self.responses += 1
                if record.request is None:
                    self.unsolicited += 1
            elif kind is _EXCEPTION:
                self.exceptions += 1
                if record.request is None:
                    self.unsolicited += 1
            elif kind is _NOISE:
                noise = record.noise
                self.noise_records += 1
                if noise is not None:
                    self.noise_bytes += len(noise.raw)
                    if "CRC" in noise.reason:
                        self.crc_errors += 1
            elif kind is _EVENT:
                event = record.event
                if event is not None:
                    self.events[event.kind.value] += 1
                    if event.kind is EventKind.TIMEOUT:
                        self.timeouts += 1
                    elif event.kind is EventKind.STATS:
                        continue  # the source's own counters, stamped when it stopped:
                        # not traffic, so not part of the time span
            elif kind is _COMMAND:
                command = record.command
                if command is not None:
                    self.commands[command.phase.value] += 1
            frame = record.frame
            if frame is not None and frame.pdu.malformed:
                self.malformed += 1
            stream = record.stream
            if stream is not None and stream.id > self.max_stream:
                self.max_stream = stream.id
                view = self.view
                if view is not None and not self.robot_seen:
                    self.robot_seen = view.robot_role(stream) is not None
            ts = record.ts
            if self.first is None or ts < self.first:
                self.first = ts
            if self.last is None or ts > self.last:
                self.last = ts

    @property
    def frames(self) -> int:
        return self.requests + self.responses + self.exceptions

    def text(self, *, timed: bool = True) -> str:
        """The summary's lines (no trailing newline)."""
        answered = self.responses + self.exceptions - self.unsolicited
        parts = [
            f"{self.frames} frames ({self.requests} requests, {answered} answered, "
            f"{self.exceptions} exceptions, {self.timeouts} unanswered, "
            f"{self.unsolicited} unsolicited) on {self.streams} streams"
        ]
        if self.noise_records or self.malformed:
            parts.append(
                f"noise: {self.noise_bytes} bytes in {self.noise_records} runs "
                f"({self.crc_errors} CRC errors); {self.malformed} malformed frames"
            )
        if self.commands:
            done = ", ".join(f"{n} {phase}" for phase, n in sorted(self.commands.items()))
            parts.append(f"robot commands: {done}")
        if timed and self.first is not None and self.last is not None:
            parts.append(f"time span: {human_span(self.last - self.first)}")
        for key, value in self.extra.items():
            parts.append(f"{key}: {value}")
        return "\n".join(parts)
