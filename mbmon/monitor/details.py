"""The monitor's details pane: the fields of the selected line as ``decode`` prints
them (:func:`mbmon.details.frame_details`), its paired request or answer, and the raw
bytes with the field under the cursor highlighted.
"""

from __future__ import annotations

from typing import Any, ClassVar

from rich.cells import cell_len
from rich.text import Text
from textual.binding import Binding

from mbmon.details import frame_details
from mbmon.model import Kind
from mbmon.monitor.feed import Entry, FeedView
from mbmon.monitor.widgets import TextPane


def entry_details(entry: Entry, snap: FeedView | None, field: int = 0) -> tuple[Text, int]:
    """The details pane's text for one kept line and the number of field lines it has.

    The line itself (whole, wrapped), every field as ``decode`` prints it
    (:func:`mbmon.details.frame_details`; the one numbered ``field`` is
    selected), the paired request or answer with the latency, and the raw
    bytes in hex with the selected field's bytes highlighted.
    """
    record = entry.record
    text = Text()
    text.append(f"#{record.index}  ", style="dim")
    text.append(entry.line)
    text.append("\n")
    frame = record.frame
    fields = 0
    if frame is not None:
        request_pdu = record.request.pdu if record.request is not None else None
        details = frame_details(frame, record.notes, request=request_pdu)
        fields = len(details)
        field = max(0, min(field, fields - 1))
        span = None
        for i, (line, where) in enumerate(details):
            chosen = i == field
            text.append("▸ " if chosen else "  ", style="bold")
            text.append(line, style="reverse" if chosen else "")
            text.append("\n")
            if chosen:
                span = where
        pair = _pair(entry, snap)
        if pair:
            text.append(pair)
        text.append(f"raw ({len(frame.raw)} bytes): ", style="dim")
        text.append_text(hex_with(frame.raw, span))
        text.append("\n")
    elif record.noise is not None:
        text.append(f"  reason: {record.noise.reason}\n")
        text.append(f"raw ({len(record.noise.raw)} bytes): ", style="dim")
        text.append_text(hex_with(record.noise.raw, None))
        text.append("\n")
    elif record.event is not None:
        for key, value in record.event.info.items():
            text.append(f"  {key}: {value}\n")
    elif record.command is not None:
        cmd = record.command
        text.append(f"  phase: {cmd.phase.value}\n")
        if cmd.code is not None:
            text.append(f"  command number: {cmd.code}\n")
        if cmd.duration is not None:
            text.append(f"  duration: {cmd.duration:.3f} s\n")
        for key, value in cmd.params.items():
            text.append(f"  {key}: {value}\n")
    return text, fields


def _pair(entry: Entry, snap: FeedView | None) -> Text:
    """The paired request (of an answer) or answer (of a request), with the latency."""
    record = entry.record
    out = Text()
    if record.request is not None:
        where = f"#{record.request_index}" if record.request_index is not None else ""
        out.append(f"request {where}: ", style="bold")
        found = _find(snap, record.request_index) if snap is not None else None
        out.append(found.line if found is not None else record.request.pdu.raw.hex(" ").upper())
        out.append("\n")
        if record.latency is not None:
            out.append(f"latency: {record.latency * 1000:.1f} ms\n", style="bold")
    elif record.frame is not None and record.frame.pdu.kind is Kind.REQUEST:
        answer = snap.answers.get(record.index) if snap is not None else None
        if answer is None:
            out.append("answer: none yet\n", style="dim")
        else:
            out.append(f"answer #{answer.record.index}: ", style="bold")
            out.append(answer.line)
            out.append("\n")
            if answer.record.latency is not None:
                out.append(f"latency: {answer.record.latency * 1000:.1f} ms\n", style="bold")
    return out


def _find(snap: FeedView, index: int | None) -> Entry | None:
    """The kept entry of record number ``index`` (records are kept in index order)."""
    if index is None:
        return None
    entries = snap.entries
    lo, hi = 0, len(entries)
    while lo < hi:
        mid = (lo + hi) // 2
        if entries[mid].record.index < index:
            lo = mid + 1
        else:
            hi = mid
    if lo < len(entries) and entries[lo].record.index == index:
        return entries[lo]
    return None


def hex_with(raw: bytes, span: tuple[int, int] | None) -> Text:
    """``raw`` as upper-case hex pairs, the bytes ``span`` (start, end) highlighted."""
    text = Text(raw.hex(" ").upper())
    if span is not None and span[1] > span[0]:
        start, end = span
        text.stylize("reverse bold", start * 3, end * 3 - 1)
    return text


class Details(TextPane, can_focus=True):
    """The details pane; ↑ ↓ pick the field whose bytes the raw hex highlights."""

    BINDINGS: ClassVar[list[Any]] = [
        Binding("up", "field(-1)", "field up", show=False),
        Binding("down", "field(1)", "field down", show=False),
    ]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(Text("no line selected", style="dim"), **kwargs)
        self.entry: Entry | None = None
        self.field = 0
        self.fields = 0
        self.snap: FeedView | None = None

    def show(self, entry: Entry | None, snap: FeedView | None, *, same: bool = False) -> None:
        if not same:
            self.field = 0
            self.top = 0
        self.entry, self.snap = entry, snap
        self._draw()

    def _draw(self) -> None:
        if self.entry is None:
            self.set_text(Text("no line selected", style="dim"))
            return
        text, self.fields = entry_details(self.entry, self.snap, self.field)
        self.set_text(text)
        # keep the selected field in sight: the line above it wraps to a few rows
        width = max(1, self.content_size.width)
        first = -(-cell_len(text.plain.split("\n", 1)[0]) // width)
        self.show_line(first + self.field)

    def action_field(self, by: int) -> None:
        if self.fields:
            self.field = max(0, min(self.fields - 1, self.field + by))
            self._draw()

    def text(self) -> str:
        """The pane's text (tests)."""
        if self.entry is None:
            return ""
        return entry_details(self.entry, self.snap, self.field)[0].plain
