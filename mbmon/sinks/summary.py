"""The end-of-run summary: what a run saw, counted from its records, for stderr.

A listener like any other (``read``, ``sniff``, ``proxy`` and ``demo`` attach
it unless ``-q``): it counts frames, transactions, exceptions, timeouts, noise
and CRC errors, commands and their outcomes, streams and the time span, and
:meth:`Summary.text` renders them as the few lines a user reads after a run.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from mbmon.model import EventKind, Phase, Record, RecordKind, Stream
from mbmon.timefmt import human_span

_REQUEST, _RESPONSE, _EXCEPTION = RecordKind.REQUEST, RecordKind.RESPONSE, RecordKind.EXCEPTION
_NOISE, _EVENT, _COMMAND = RecordKind.NOISE, RecordKind.EVENT, RecordKind.COMMAND
_WRITTEN, _EXECUTING, _WARNING = Phase.WRITTEN, Phase.EXECUTING, Phase.WARNING
_OUTCOMES = (Phase.SUCCESS, Phase.FAIL)

#: How a command that has not ended is named in the summary, by its last phase.
_OPEN_NAMES = {_WRITTEN: "written, not executed", _EXECUTING: "executing, no status"}


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
        #: robot commands by final outcome, each command once: "success", "fail",
        #: "executing, no status" (executed, then another command or the end came
        #: first) and "written, not executed"; warnings are counted apart
        self.commands: Counter[str] = Counter()
        self.warnings = 0
        #: the command not yet ended per (stream id, unit): its last phase
        self._open: dict[tuple[int, int], Phase] = {}
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
            elif not self._other(record):
                continue  # the source's own counters, stamped when it stopped:
                # not traffic, so not part of the time span
            frame = record.frame
            if frame is not None and frame.pdu.malformed:
                self.malformed += 1
            stream = record.stream
            if stream is not None and stream.id > self.max_stream:
                self._new_stream(stream)
            ts = record.ts
            if self.first is None or ts < self.first:
                self.first = ts
            if self.last is None or ts > self.last:
                self.last = ts

    def _other(self, record: Record) -> bool:
        """Count a noise run, an event or a command step; ``False`` for a source's
        closing statistics (no part of the traffic)."""
        kind = record.kind
        if kind is _NOISE:
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
                    return False
        elif kind is _COMMAND:
            command = record.command
            if command is not None:
                self._command(command.stream.id, command.unit, command.phase)
        return True

    def _new_stream(self, stream: Stream) -> None:
        """A stream with a higher id than any so far: the count, and whether the robot
        ``--robot`` names is one of its ends."""
        self.max_stream = stream.id
        view = self.view
        if view is not None and not self.robot_seen:
            self.robot_seen = view.robot_role(stream) is not None

    def _command(self, sid: int, unit: int, phase: Phase) -> None:
        """One step of a command's life (written, executing, success/fail, returned):
        a command is counted once, when its outcome is known or another replaces it."""
        key = (sid, unit)
        if phase is _WARNING:
            self.warnings += 1
        elif phase in _OUTCOMES:
            if self._open.pop(key, None) is not None:
                self.commands[phase.value] += 1
        elif phase is _EXECUTING:
            if self._open.get(key) is _EXECUTING:
                self.commands[_OPEN_NAMES[_EXECUTING]] += 1  # executed again before a status
            self._open[key] = _EXECUTING
        elif phase is _WRITTEN:
            if self._open.get(key) is _EXECUTING:
                self.commands[_OPEN_NAMES[_EXECUTING]] += 1
            self._open[key] = _WRITTEN  # a block rewritten before execution: still one
        # RETURNED: the values a Get command's success brought back, not a command

    def command_counts(self) -> Counter[str]:
        """Each robot command once, by its final outcome so far (see :attr:`commands`)."""
        counts = Counter(self.commands)
        for phase in self._open.values():
            counts[_OPEN_NAMES[phase]] += 1
        return counts

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
        counts = self.command_counts()
        if counts or self.warnings:
            order = ["success", "fail", _OPEN_NAMES[_EXECUTING], _OPEN_NAMES[_WRITTEN]]
            done = ", ".join(f"{counts[name]} {name}" for name in order if counts[name])
            total = sum(counts.values())
            line = f"robot commands: {total}" + (f" ({done})" if done else "")
            if self.warnings:
                line += f"; {self.warnings} warning{'s' if self.warnings != 1 else ''}"
            parts.append(line)
        if timed and self.first is not None and self.last is not None:
            parts.append(f"time span: {human_span(self.last - self.first)}")
        for key, value in self.extra.items():
            parts.append(f"{key}: {value}")
        return "\n".join(parts)
