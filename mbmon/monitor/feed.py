"""The monitor's listener: what the screen shows, kept in the hub's thread.

:class:`MonitorFeed` is a hub listener (DESIGN rule 7). In the hub's thread it
keeps the last :data:`KEEP` records with their monitor line (made by
:func:`mbmon.format.record_line` with the command's view: the line ``read``
prints), the raw input around them (for ``w`` saves to ``.mcap``/``.pcap``),
counts and rates, the register image (:class:`RegisterImage`), and with a
profile that has a device session the robot state, the last command and the
session's panel (:meth:`mbmon.semantics.session.Session.panel`: for HRSS the
written command registers).

The screen (:mod:`mbmon.monitor.app`, another thread) only reads, through
:meth:`MonitorFeed.view`: a consistent copy taken under the feed's lock. The
hub never waits for the screen: a paused, slow or absent screen changes
nothing the logs and counts get. Nothing here imports textual.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from mbmon.format import View, record_line
from mbmon.model import Chunk, Event, EventKind, Kind, Record, RecordKind
from mbmon.protocol.functions import SHAPE
from mbmon.protocol.pdu import table_of

__all__ = ["KEEP", "Entry", "FeedView", "MonitorFeed", "RegisterImage"]

#: Records the monitor keeps to scroll back through (the robot's own monitor keeps 200).
KEEP = 10_000
#: Raw chunks and events kept per kept record (for ``w`` to ``.mcap`` and ``.pcap``).
INPUTS_PER_RECORD = 4
#: Seconds over which frames/s is computed.
RATE_WINDOW = 2.0

#: The table letters of the register image: ``R`` holding, ``IR`` input register,
#: ``C`` coil, ``DI`` discrete input (as the HRSS manual names registers).
TABLE_PREFIX = {
    "holding_register": "R",
    "input_register": "IR",
    "coil": "C",
    "discrete_input": "DI",
}


@dataclass(frozen=True, slots=True)
class Entry:
    """One kept record: its number in the run (``seq``, from 0), the record, its line."""

    seq: int
    record: Record
    line: str


@dataclass(slots=True)
class Cell:
    """One register or coil of the image: its value, when it last changed, when it was
    first and last seen (times of the traffic)."""

    value: int
    changed: float
    seen: float
    first: float


class RegisterImage:
    """Every register and coil seen on the wire, per server, unit and table.

    Read answers (FC 01..04) give the values read; answered writes (FC 05, 06,
    0F, 10) the values written. ``cells[(server, unit, table, address)]`` holds
    a :class:`Cell`. A read whose answer repeats the last one for the same block
    costs one comparison (polling leaves the image as it was).
    """

    def __init__(self) -> None:
        self.cells: dict[tuple[str, int, str, int], Cell] = {}
        self._blocks: dict[tuple[str, int, str, int], tuple[int, ...]] = {}
        #: grows whenever a value changes or a cell is added (the screen redraws then)
        self.version = 0

    def take(self, record: Record) -> None:
        """Apply one record (a read's answer or a write's answer); others change nothing."""
        frame, request = record.frame, record.request
        if frame is None or request is None or record.kind is not RecordKind.RESPONSE:
            return
        req = request.pdu
        fc = req.fc
        if req.address is None or req.malformed:
            return
        shape = SHAPE.get(fc)
        table = table_of(fc)
        if table is None:
            return
        if shape == "read":
            values = frame.pdu.values
            if values is not None and req.count is not None:
                values = values[: req.count]  # bits past the count are padding
        elif shape == "write_single" or shape == "write_multiple":
            values = req.values
        else:
            return
        if not values:
            return
        server = frame.stream.server
        key = (server, frame.unit, table, req.address)
        if self._blocks.get(key) == values:
            return
        self._blocks[key] = values
        self.version += 1
        ts = record.ts
        cells = self.cells
        for i, value in enumerate(values):
            at = (server, frame.unit, table, req.address + i)
            cell = cells.get(at)
            if cell is None:
                cells[at] = Cell(value, ts, ts, ts)
            else:
                cell.seen = ts
                if cell.value != value:
                    cell.value = value
                    cell.changed = ts

    def values(self) -> dict[tuple[str, int, str, int], int]:
        """The image's values now (what a snapshot keeps)."""
        return {key: cell.value for key, cell in self.cells.items()}

    def copy(self) -> dict[tuple[str, int, str, int], Cell]:
        """The cells now, copied (for the screen's thread)."""
        return {key: Cell(c.value, c.changed, c.seen, c.first) for key, c in self.cells.items()}


def register_name(key: tuple[str, int, str, int]) -> str:
    """A register or coil as the HRSS manual writes it: ``R200``, ``IR2``, ``C5``, ``DI1``."""
    _server, _unit, table, address = key
    return f"{TABLE_PREFIX.get(table, table)}{address}"


@dataclass(slots=True)
class FeedView:
    """What the screen reads at one refresh: a copy, consistent, owned by the screen."""

    entries: list[Entry]
    total: int
    counts: dict[str, int]
    figures: dict[str, Any]
    rate: float
    state: dict[str, float]
    command: Any
    parameters: list[tuple[str, str, str, bool]]
    registers: dict[tuple[str, int, str, int], Cell] | None
    registers_version: int
    ended: bool
    version: int
    answers: dict[int, Entry] = field(default_factory=dict)
    panel_title: str = ""  # the session panel's title (its rows are ``parameters``)


class MonitorFeed:
    """The hub listener behind the interactive monitor (see the module text)."""

    name = "monitor"

    def __init__(
        self,
        view: View,
        *,
        title: str = "mbmon",
        keep: int = KEEP,
        annotator: Any = None,
        profile: bool = False,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.view = view
        self.title = title
        self.keep = keep
        #: an HRSS profile is in force: the robot panel and parameter registers are shown
        self.profile = profile
        self._clock = clock
        self._lock = threading.Lock()
        self._entries: deque[Entry] = deque(maxlen=keep)
        self._inputs: deque[Chunk | Event] = deque(maxlen=keep * INPUTS_PER_RECORD)
        self._answers: dict[int, Entry] = {}  # request record index -> its answer's entry
        self._seq = 0
        self.counts: dict[str, int] = {
            "frames": 0,
            "requests": 0,
            "responses": 0,
            "exceptions": 0,
            "timeouts": 0,
            "noise_bytes": 0,
            "open_connections": 0,
        }
        self.figures: dict[str, Any] = {}
        self.state: dict[str, float] = {}
        self.command: Any = None
        self.registers = RegisterImage()
        self.parameters: list[tuple[str, str, str, bool]] = []
        self.panel_title = ""
        self._sessions: Any = getattr(annotator, "sessions", None)
        self._robot: tuple[str, int] | None = None
        self.rate = 0.0
        self._samples: deque[tuple[float, int]] = deque()
        #: the input has ended (the source is done; the screen stays until q)
        self.ended = False
        self._version = 0

    # ------------------------------------------------------------------ hooks (hub thread)

    def on_chunk(self, chunk: Chunk) -> None:
        self._inputs.append(chunk)

    def on_event(self, event: Event) -> None:
        self._inputs.append(event)

    def on_records(self, records: list[Record]) -> None:
        with self._lock:  # the screen copies under it: never a half-applied batch
            self._take(records)

    def _take(self, records: list[Record]) -> None:
        counts = self.counts
        view = self.view
        entries = self._entries
        answers = self._answers
        registers = self.registers
        seq = self._seq
        for record in records:
            kind = record.kind
            frame = record.frame
            if frame is not None:
                counts["frames"] += 1
                if kind is RecordKind.REQUEST:
                    counts["requests"] += 1
                elif kind is RecordKind.RESPONSE:
                    counts["responses"] += 1
                    if record.request is not None:
                        registers.take(record)
                else:
                    counts["exceptions"] += 1
            elif kind is RecordKind.NOISE and record.noise is not None:
                counts["noise_bytes"] += len(record.noise.raw)
            elif kind is RecordKind.EVENT and record.event is not None:
                ek = record.event.kind
                if ek is EventKind.TIMEOUT:
                    counts["timeouts"] += 1
                elif ek is EventKind.CONNECT:
                    counts["open_connections"] += 1
                elif ek is EventKind.DISCONNECT:
                    counts["open_connections"] = max(0, counts["open_connections"] - 1)
            elif kind is RecordKind.COMMAND and record.command is not None:
                self.command = cmd = record.command
                self._robot = (cmd.stream.server, cmd.unit)
            if record.state:
                self.state.update(record.state)
                if frame is not None:
                    self._robot = (frame.stream.server, frame.unit)
            if len(entries) == self.keep:
                answers.pop(entries[0].record.index, None)
            entry = Entry(seq, record, record_line(record, view))
            entries.append(entry)
            if record.request_index is not None and frame is not None:
                answers[record.request_index] = entry
            seq += 1
        self._seq = seq
        self._version += 1

    def on_tick(self, now: float) -> None:
        samples = self._samples
        samples.append((now, self.counts["frames"]))
        while len(samples) > 2 and now - samples[0][0] > RATE_WINDOW:
            samples.popleft()
        t0, n0 = samples[0]
        self.rate = (self.counts["frames"] - n0) / (now - t0) if now > t0 else 0.0
        if self._sessions is not None:
            panel = _panel(self._sessions(), self._robot)
            with self._lock:
                self.parameters = list(panel.rows) if panel is not None else []
                self.panel_title = panel.title if panel is not None else ""
        with self._lock:
            self._version += 1

    # ------------------------------------------------------------------ for commands

    def set_figure(self, name: str, value: Any) -> None:
        """A figure of the command's own shown in the header (e.g. ``kernel drops``).

        ``open connections`` replaces the monitor's own count (connects minus
        disconnects seen), which misses connections opened before the capture
        began: a source that knows its open connections (the packet dissector)
        gives the true figure."""
        with self._lock:
            self.figures[name] = value

    def set_figures(self, figures: Mapping[str, Any]) -> None:
        with self._lock:
            self.figures.update(figures)

    def end(self) -> None:
        """The input has ended (the command's run returned): the header says so."""
        with self._lock:
            self.ended = True
            self._version += 1

    # ------------------------------------------------------------------ for the screen

    @property
    def total(self) -> int:
        """Records taken so far (kept or not)."""
        return self._seq

    @property
    def version(self) -> int:
        """Grows whenever something shown may have changed (the screen redraws only then)."""
        return self._version

    def snapshot(self, registers_seen: int = -1) -> FeedView:
        """A consistent copy of what the screen shows (taken under the lock, in any thread).

        The register image is copied only when it changed since version
        ``registers_seen`` (``registers`` is then ``None``: the caller's copy holds)."""
        with self._lock:
            image = self.registers
            cells = image.copy() if image.version != registers_seen else None
            return FeedView(
                entries=list(self._entries),
                total=self._seq,
                counts=dict(self.counts),
                figures=dict(self.figures),
                rate=self.rate,
                state=dict(self.state),
                command=self.command,
                parameters=list(self.parameters),
                registers=cells,
                registers_version=image.version,
                ended=self.ended,
                version=self._version,
                answers=dict(self._answers),
                panel_title=self.panel_title,
            )

    def inputs_between(self, t0: float, t1: float) -> list[Chunk | Event]:
        """The raw chunks and events kept whose time is within ``[t0, t1]``."""
        with self._lock:
            return [item for item in self._inputs if t0 <= item.ts <= t1]

    def header_text(self) -> str:
        """The header's text: title, rate, counts and the command's own figures."""
        return header_text(self.title, self.snapshot())


def header_text(title: str, snap: FeedView) -> str:
    """The monitor's header as plain text (one home for its words)."""
    return "  ".join(f"{label} {value}" if label else str(value) for label, value in
                     header_items(title, snap))  # fmt: skip


def header_items(title: str, snap: FeedView) -> list[tuple[str, Any]]:
    """``(label, value)`` pairs of the header, in order (the title's label is empty)."""
    c = snap.counts
    items: list[tuple[str, Any]] = [
        ("", title),
        ("", f"{snap.rate:.1f} frames/s"),
        ("frames", c["frames"]),
        ("requests", c["requests"]),
        ("responses", c["responses"]),
        ("exceptions", c["exceptions"]),
        ("timeouts", c["timeouts"]),
        ("noise bytes", c["noise_bytes"]),
        ("open connections", snap.figures.get("open connections", c["open_connections"])),
    ]
    items.extend((k, v) for k, v in snap.figures.items() if k != "open connections")
    return items


def _panel(sessions: Mapping[tuple[str, int], Any], robot: tuple[str, int] | None) -> Any:
    """The panel of the robot shown's device session (``None`` without a session)."""
    session = sessions.get(robot) if robot is not None else None
    if session is None and len(sessions) == 1:
        session = next(iter(sessions.values()))
    return session.panel() if session is not None else None


def is_request(record: Record) -> bool:
    """Whether a record is a request frame (its answer is looked up by its index)."""
    return record.frame is not None and record.frame.pdu.kind is Kind.REQUEST


def entries_in(entries: Iterable[Entry], first: int, last: int) -> list[Entry]:
    """The entries numbered ``first..last`` (inclusive)."""
    return [e for e in entries if first <= e.seq <= last]
