"""The interactive monitor's screen, on textual (imported only when a monitor runs).

:class:`MonitorApp` shows a :class:`~mbmon.monitor.feed.MonitorFeed`: a header
with counts and rates, the monitor list (the lines ``read`` prints, newest at
the bottom), a details pane for the selected line (the fields ``decode``
prints, from :func:`mbmon.format.frame_details`, the paired request or
answer, latency, notes, the raw bytes with the field under the cursor
highlighted), and, when there is room or on ``r``, the robot panel and the
register image. Keys are listed in :data:`HELP` (``?`` on the screen).

The screen never drives the capture: it looks at the feed :data:`REDRAWS`
times a second and copies and redraws it, when something changed, at most
:data:`DATA_REDRAWS` times a second (keys are answered at once). The lines come
made from the hub's thread; the details are made here from the kept records
(format's text caches are dicts: two threads at worst compute a text twice).
Every text from the wire is a :class:`rich.text.Text` (never markup), so
untrusted bytes cannot style the screen.
"""

from __future__ import annotations

import argparse
import bisect
import shlex
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

from rich.cells import cell_len
from rich.segment import Segment
from rich.style import Style
from rich.text import Text
from textual import events
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.screen import ModalScreen
from textual.strip import Strip
from textual.widget import Widget
from textual.widgets import Footer, Input, Static

from mbmon.format import frame_details
from mbmon.model import Kind, RecordKind
from mbmon.monitor.feed import Cell, Entry, FeedView, MonitorFeed, header_items, register_name

#: The screen looks at the feed this many times a second (and answers keys at once);
REDRAWS = 10
#: but redraws for new traffic at most this many times a second: a redraw moves every
#: row of the list, and nobody reads faster (at 5,000 frames/s it keeps the screen
#: under 10 % of a core: bench/monitor_load.py)
DATA_REDRAWS = 4
#: A register changed within this many seconds (of the traffic's time) is highlighted.
CHANGED_FOR = 2.0
#: The side column (robot panel, register image) shows by itself from this width on.
SIDE_FROM = 120


def _time_text() -> Callable[[float], str]:
    """Times of day for the side panes, from a time format of the screen's own: the
    one format.format_time uses keeps a per-second cache the hub's thread writes."""
    from mbmon.timefmt import TimeFormat

    return TimeFormat(auto_date=False).text


format_time = _time_text()

HELP = """\
mbmon monitor: keys

  space        pause / resume the view (capture, logs and counts go on)
  ↑ ↓ PgUp PgDn Home End   move in the list (End: follow the newest again)
  ← →          scroll long lines sideways (the details pane shows them whole)
  tab          move between the list, the details (↑ ↓ there pick a field: its
               bytes are highlighted in the raw hex; PgUp PgDn scroll) and the
               register image (↑ ↓ PgUp PgDn scroll it)
  /            search the lines (the same text as --grep, any case)
  n  N         next / previous match
  f            display filter, the command-line syntax:
               --unit 1 --fc 3,16 --address 200-251 --grep PTP  (empty: none)
  s            snapshot of the register image
  d            show what changed since the snapshot (d again: the whole image)
  m            mark / unmark the selected line
  '            jump to the next mark
  w            write the kept lines (the marked range with two marks or more)
               to a file in any -w format: .mcap .jsonl .csv .txt .pcap
  r            show / hide the robot panel and register image
  q  ctrl+c    stop: logs are finished, the summary follows the screen
  ?            this help (escape closes it)
"""

_KIND_STYLE = {
    RecordKind.REQUEST: Style(),
    RecordKind.RESPONSE: Style(color="green"),
    RecordKind.EXCEPTION: Style(color="red", bold=True),
    RecordKind.NOISE: Style(color="yellow"),
    RecordKind.EVENT: Style(color="cyan"),
    RecordKind.COMMAND: Style(color="magenta"),
}
_CURSOR = Style(reverse=True)
_MARK = Style(color="yellow", bold=True)
_MATCH = Style(bgcolor="dark_blue")
_PHASE_STYLE = {"success": "green", "fail": "bold red", "warning": "yellow"}
_STATE_CELLS = (
    ("A1", "a1"), ("A2", "a2"), ("A3", "a3"), ("A4", "a4"), ("A5", "a5"), ("A6", "a6"),
    ("X", "x"), ("Y", "y"), ("Z", "z"), ("A", "a"), ("B", "b"), ("C", "c"),
)  # fmt: skip


class FilterSyntaxError(ValueError):
    """A display filter the command-line filter syntax does not accept."""


class _FilterParser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # argparse would exit the program
        raise FilterSyntaxError(message)


def parse_display_filter(text: str) -> Any:
    """The :class:`~mbmon.filters.RecordFilter` for ``text`` in the command-line syntax
    (``--unit 1 --fc 3 --address 200-251 --grep PTP``); ``None`` for an empty text.
    Raises :class:`FilterSyntaxError` with the reason for anything else."""
    from mbmon.filters import FilterError, add_filter_options, build_filter

    if not text.strip():
        return None
    parser = _FilterParser(prog="f", add_help=False, exit_on_error=False)
    add_filter_options(parser)
    try:
        args = parser.parse_args(shlex.split(text))
        return build_filter(args, start_known=False)
    except (FilterError, ValueError, argparse.ArgumentError) as exc:
        raise FilterSyntaxError(str(exc)) from None


# --------------------------------------------------------------------------- the list


class MonitorList(Widget, can_focus=True):
    """The monitor lines, one row each, with the cursor, marks and sideways scrolling.

    It scrolls itself (``top``: the first row shown, ``x``: the first column) rather
    than through textual's virtual size, whose every change lays the whole screen
    out again: a new line then costs the redraw of this pane only. The border says
    which lines are shown (``a-b of n``)."""

    BINDINGS: ClassVar[list[Any]] = [
        Binding("up", "move(-1)", "up", show=False),
        Binding("down", "move(1)", "down", show=False),
        Binding("pageup", "page(-1)", "PgUp", show=False),
        Binding("pagedown", "page(1)", "PgDn", show=False),
        Binding("home", "first", "Home", show=False),
        Binding("end", "last", "End", show=False),
        Binding("left", "sideways(-8)", "left", show=False),
        Binding("right", "sideways(8)", "right", show=False),
    ]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.rows: list[Entry] = []
        self._seqs: list[int] = []
        self.cursor = -1  # index into rows; -1 with follow
        self.follow = True
        self.marks: set[int] = set()  # seq numbers
        self.query_text = ""
        self.top = 0  # the first row shown
        self.x = 0  # the first column shown
        self._width = 0
        self._measured = -1  # the lines up to this seq are measured

    @property
    def height_rows(self) -> int:
        return max(1, self.content_size.height)

    # -- data
    def set_rows(self, rows: list[Entry]) -> None:
        """Show ``rows`` (ordered by seq), keeping the selected line where it was on screen."""
        old_seq = self.rows[self.cursor].seq if 0 <= self.cursor < len(self.rows) else None
        offset = self.cursor - self.top
        self.rows = rows
        self._seqs = seqs = [e.seq for e in rows]
        width = self._width
        # measure only the lines not measured yet (the width of the widest line seen);
        # len() for speed: a monitor line's characters take one cell each
        for e in rows[bisect.bisect_right(seqs, self._measured) :]:
            n = len(e.line)
            if n > width:
                width = n
        if rows:
            self._measured = max(self._measured, seqs[-1])
        self._width = width
        if self.follow or old_seq is None:
            self.cursor = len(rows) - 1
            self.top = max(0, len(rows) - self.height_rows)
        else:
            i = bisect.bisect_left(seqs, old_seq)
            self.cursor = min(i, len(rows) - 1)
            self.top = self._clamp_top(self.cursor - offset)
        self._changed()

    def _clamp_top(self, top: int) -> int:
        return max(0, min(top, len(self.rows) - self.height_rows))

    def _changed(self) -> None:
        n = len(self.rows)
        where = f"{self.top + 1}-{min(n, self.top + self.height_rows)} of {n}" if n else ""
        if self.x:
            where += f", from column {self.x + 1}"
        if where != self.border_subtitle:
            self.border_subtitle = where
        self.refresh()

    def on_resize(self, event: events.Resize) -> None:
        if self.follow:
            self.top = self._clamp_top(len(self.rows))
        self._changed()

    def index_of(self, seq: int) -> int | None:
        i = bisect.bisect_left(self._seqs, seq)
        return i if i < len(self._seqs) and self._seqs[i] == seq else None

    @property
    def selected(self) -> Entry | None:
        return self.rows[self.cursor] if 0 <= self.cursor < len(self.rows) else None

    def select(self, index: int, *, follow: bool | None = None) -> None:
        if not self.rows:
            return
        index = max(0, min(index, len(self.rows) - 1))
        self.cursor = index
        self.follow = (index == len(self.rows) - 1) if follow is None else follow
        height = self.height_rows
        if index < self.top:
            self.top = index
        elif index >= self.top + height:
            self.top = index - height + 1
        self.top = self._clamp_top(self.top)
        self._changed()
        self.post_message(self.Moved())

    class Moved(events.Message):
        """The selected line changed."""

    # -- keys and mouse
    def action_move(self, by: int) -> None:
        self.select(self.cursor + by, follow=False)

    def action_page(self, by: int) -> None:
        self.select(self.cursor + by * max(1, self.height_rows - 1), follow=False)

    def action_first(self) -> None:
        self.select(0, follow=False)

    def action_last(self) -> None:
        self.select(len(self.rows) - 1, follow=True)

    def action_sideways(self, by: int) -> None:
        room = max(0, self._width + 2 - self.content_size.width)
        self.x = max(0, min(self.x + by, room))
        self._changed()

    def on_mouse_scroll_down(self, event: events.MouseScrollDown) -> None:
        self.top = self._clamp_top(self.top + 3)
        self.follow = False
        self._changed()

    def on_mouse_scroll_up(self, event: events.MouseScrollUp) -> None:
        self.top = self._clamp_top(self.top - 3)
        self.follow = False
        self._changed()

    def on_click(self, event: events.Click) -> None:
        at = event.get_content_offset(self)
        if at is not None:
            self.select(self.top + at.y, follow=False)

    # -- drawing
    def render_line(self, y: int) -> Strip:
        index = self.top + y
        width = self.content_size.width
        if index >= len(self.rows) or y >= self.height_rows:
            return Strip.blank(width)
        entry = self.rows[index]
        here = "›" if index == self.cursor else " "
        mark = "●" if entry.seq in self.marks else " "
        style = _KIND_STYLE.get(entry.record.kind, Style())
        line = entry.line
        segments = [Segment(here), Segment(mark, _MARK)]
        q = self.query_text.lower()
        at = line.lower().find(q) if q else -1
        if at >= 0:
            segments += [
                Segment(line[:at], style),
                Segment(line[at : at + len(q)], style + _MATCH),
                Segment(line[at + len(q) :], style),
            ]
        else:
            segments.append(Segment(line, style))
        strip = Strip(segments)
        if self.x:
            strip = Strip.join([strip.crop(0, 2), strip.crop(2 + self.x)])
        strip = strip.crop_extend(0, width, None)
        if index == self.cursor:
            strip = strip.apply_style(_CURSOR if self.has_focus else Style(bgcolor="grey30"))
        return strip


# --------------------------------------------------------------------------- details


def entry_details(entry: Entry, snap: FeedView | None, field: int = 0) -> tuple[Text, int]:
    """The details pane's text for one kept line and the number of field lines it has.

    The line itself (whole, wrapped), every field as ``decode`` prints it
    (:func:`mbmon.format.frame_details`; the one numbered ``field`` is
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


class TextPane(Widget):
    """A pane of text that scrolls by whole lines and never lays the screen out again
    when its text changes (a redraw of its own region only: the cheap way to show
    text that changes several times a second). PgUp/PgDn scroll it when focused."""

    BINDINGS: ClassVar[list[Any]] = [
        Binding("pageup", "scroll_lines(-1)", "PgUp", show=False),
        Binding("pagedown", "scroll_lines(1)", "PgDn", show=False),
    ]

    def __init__(self, text: Text | None = None, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._text = text if text is not None else Text()
        self.top = 0  # the first line shown
        self.total = 0  # lines of the text at the pane's width
        self._wrapped: tuple[int, Any] | None = None  # (width, the text's lines at it)

    def set_text(self, text: Text) -> None:
        self._text = text
        self._wrapped = None
        self.refresh()

    def render(self) -> Text:
        width = max(1, self.content_size.width)
        height = max(1, self.content_size.height)
        if self._wrapped is None or self._wrapped[0] != width:
            self._wrapped = (width, self._text.wrap(self.app.console, width, overflow="fold"))
        lines = self._wrapped[1]
        self.total = len(lines)
        self.top = max(0, min(self.top, self.total - height))
        shown = Text("\n").join(lines[self.top : self.top + height])
        more = self.total > height
        where = f"{self.top + 1}-{min(self.total, self.top + height)} of {self.total}"
        subtitle = where if more else ""
        if subtitle != self.border_subtitle:
            self.border_subtitle = subtitle
        return shown

    def show_line(self, row: int) -> None:
        """Scroll so that wrapped line ``row`` is in sight."""
        height = max(1, self.content_size.height)
        if row < self.top or row >= self.top + height:
            self.top = max(0, row - height // 2)
            self.refresh()

    def action_scroll_lines(self, pages: int) -> None:
        self.top = max(0, self.top + pages * max(1, self.content_size.height - 1))
        self.refresh()


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


# --------------------------------------------------------------------------- side panes


def robot_text(snap: FeedView, columns: int = 3) -> Text:
    """The robot panel: A1..A6, X..C, speed, motion state, the last command and outcome."""
    state = snap.state
    text = Text()
    for i, (label, key) in enumerate(_STATE_CELLS):
        value = state.get(key)
        cell = f"{label:>2} {value:9.3f}" if value is not None else f"{label:>2}         —"
        text.append(cell)
        text.append("\n" if i % columns == columns - 1 else "  ")
    for label, key, fmt in (
        ("speed", "speed_pct", "{:.0f} %"),
        ("motion state", "motion_state", "{:.0f}"),
        ("TCP speed", "tcp_speed", "{:.1f}"),
    ):
        value = state.get(key)
        text.append(f"{label} ")
        text.append(fmt.format(value) if value is not None else "—", style="bold")
        text.append("\n")
    cmd = snap.command
    text.append("last command")
    if cmd is not None:
        text.append(f" ({format_time(cmd.ts)})", style="dim")
    text.append(": ")
    if cmd is None:
        text.append("—", style="dim")
    else:
        phase = cmd.phase.value
        style = _PHASE_STYLE.get(phase, "bold")
        text.append(str(cmd.text))
        text.append(f"  [{phase}", style=style)
        if cmd.duration is not None:
            text.append(f" after {cmd.duration:.3f} s", style=style)
        text.append("]", style=style)
    if snap.parameters:
        text.append(f"\n{snap.panel_title} (? = not answered yet)\n", style="dim")
        for regs, name, shown, confirmed in snap.parameters:
            text.append(f"{regs} ", style="dim")
            if name:
                text.append(f"{name} ", style="bold")
            text.append(shown, style="" if confirmed else "yellow")
            text.append("\n" if confirmed else " ?\n", style="yellow")
    return text


def registers_text(
    cells: dict[tuple[str, int, str, int], Cell],
    snapshot: dict[tuple[str, int, str, int], int] | None,
    *,
    diff: bool,
    now: float,
) -> Text:
    """The register image: every register and coil seen, its value, when it last changed;
    changed within :data:`CHANGED_FOR` s highlighted. ``diff``: only what differs from
    ``snapshot`` (``old → new``)."""
    text = Text()
    servers = {key[0] for key in cells}
    units = {(key[0], key[1]) for key in cells}
    if diff:
        if snapshot is None:
            return Text("no snapshot: s takes one", style="dim")
        keys = sorted(set(cells) | set(snapshot))
        changed = [k for k in keys if snapshot.get(k) != (cells[k].value if k in cells else None)]
        text.append(f"changed since the snapshot: {len(changed)}\n", style="bold")
        for key in changed:
            old = snapshot.get(key)
            new = cells[key].value if key in cells else None
            text.append(_where(key, len(servers) > 1, len(units) > 1))
            text.append(f" {'—' if old is None else old} → ", style="dim")
            text.append(f"{'—' if new is None else new}", style="bold yellow")
            if key in cells:
                text.append(f"  {format_time(cells[key].changed)}", style="dim")
            text.append("\n")
        return text
    if not cells:
        return Text("no register or coil seen yet", style="dim")
    for key in sorted(cells):
        cell = cells[key]
        hot = cell.changed > cell.first and now - cell.changed < CHANGED_FOR
        text.append(_where(key, len(servers) > 1, len(units) > 1))
        text.append(f" {cell.value}", style="bold yellow reverse" if hot else "bold")
        text.append(f"  {format_time(cell.changed)}\n", style="dim")
    return text


def _where(key: tuple[str, int, str, int], server: bool, unit: bool) -> str:
    prefix = f"{key[0]} " if server else ""
    prefix += f"u{key[1]} " if unit else ""
    return prefix + register_name(key)


class Registers(TextPane, can_focus=True):
    """The register image; ↑ ↓ PgUp PgDn scroll it when focused (tab)."""

    BINDINGS: ClassVar[list[Any]] = [
        Binding("up", "scroll_by(-1)", "up", show=False),
        Binding("down", "scroll_by(1)", "down", show=False),
    ]

    def action_scroll_by(self, lines: int) -> None:
        self.top = max(0, self.top + lines)
        self.refresh()


class HelpScreen(ModalScreen[None]):
    """``?``: the keys."""

    BINDINGS: ClassVar[list[Any]] = [
        Binding("escape", "app.pop_screen", "close"),
        Binding("question_mark", "app.pop_screen", "close"),
        Binding("q", "app.pop_screen", "close"),
    ]
    DEFAULT_CSS = """
    HelpScreen { align: center middle; }
    HelpScreen > VerticalScroll { width: 90%; max-width: 84; height: 90%;
        border: round $accent; background: $surface; padding: 0 1; }
    """

    def compose(self) -> ComposeResult:
        with VerticalScroll():
            yield Static(Text(HELP))


# --------------------------------------------------------------------------- the app


def _stdout_driver() -> Any:
    """A subclass of textual's Linux driver that writes to stdout (``None`` elsewhere)."""
    try:
        from textual.drivers.linux_driver import LinuxDriver
    except ImportError:
        return None

    class StdoutDriver(LinuxDriver):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._file = sys.__stdout__

    return StdoutDriver


_StdoutDriver = _stdout_driver()


class MonitorApp(App[None]):
    """The interactive monitor (see the module text)."""

    TITLE = "mbmon"
    ENABLE_COMMAND_PALETTE = False
    CSS = """
    Screen { layout: vertical; }
    #header { height: 2; background: $boost; }
    #main { height: 1fr; }
    #left { width: 1fr; }
    MonitorList { height: 1fr; border: round $primary-darken-2; }
    MonitorList:focus { border: round $accent; }
    Details { height: 40%; min-height: 5; border: round $primary-darken-2; }
    Details:focus { border: round $accent; }
    #side { width: 46; display: none; }
    #side.shown { display: block; }
    #robot { height: 55%; border: round $primary-darken-2; }
    #registers { height: 1fr; border: round $primary-darken-2; }
    #registers:focus { border: round $accent; }
    #prompt { dock: bottom; display: none; }
    #prompt.shown { display: block; }
    """

    BINDINGS: ClassVar[list[Any]] = [
        Binding("space", "pause", "pause"),
        Binding("slash", "ask('search')", "search"),
        Binding("n", "next_match(1)", "next", show=False),
        Binding("N", "next_match(-1)", "prev", show=False),
        Binding("f", "ask('filter')", "filter"),
        Binding("s", "snapshot", "snapshot"),
        Binding("d", "diff", "diff"),
        Binding("m", "mark", "mark"),
        Binding("apostrophe", "next_mark", "→mark"),
        Binding("w", "ask('write')", "write"),
        Binding("r", "side", "robot/regs"),
        Binding("question_mark", "help", "help"),
        Binding("q", "stop", "quit"),
        Binding("ctrl+c", "stop", "quit", show=False, priority=True),
        Binding("escape", "cancel", "cancel", show=False),
    ]

    def __init__(
        self,
        feed: MonitorFeed,
        *,
        worker: threading.Thread | None = None,
        stop: Callable[[], None] | None = None,
        save: Callable[[str, list[Entry]], str] | None = None,
        ended_note: str = "input ended; q quits",
        display_filter: str = "",
    ) -> None:
        super().__init__()
        self._first_filter = display_filter
        self.feed = feed
        self.worker = worker
        self._stop = stop
        self._save = save
        self.ended_note = ended_note
        self.paused = False
        self.stopping = False
        #: a signal (SIGINT/SIGTERM) asked the command to stop: leave once it has
        self.signalled = False
        self.snap: FeedView = feed.snapshot()
        self._shown_version = -1
        self._frozen: list[Entry] | None = None
        self._filter: Any = None
        self.filter_text = ""
        self._filtered: list[Entry] = []
        self._filtered_upto = -1
        self.snapshot_values: dict[tuple[str, int, str, int], int] | None = None
        self.diff = False
        self.side_forced: bool | None = None
        self._laid_out: tuple[Any, ...] = ()
        self._drawn_at = 0.0
        self._drawn_robot: Any = None
        self._drawn_registers: Any = None
        self._asking = ""
        self.search_text = ""
        self.redraws = 0
        #: what was printed to stdout/stderr while the screen ran (shown after it closes)
        self.captured: list[str] = []
        self._captured_lock = threading.Lock()

    def get_driver_class(self) -> Any:
        """Textual's own driver, drawing on stdout (textual's draws on stderr): the screen
        is what stdout shows, and stderr may go elsewhere (``2> errors.log``)."""
        driver = super().get_driver_class()
        try:
            from textual.drivers.linux_driver import LinuxDriver
        except ImportError:  # not on this platform
            return driver
        if _StdoutDriver is None or not (
            isinstance(driver, type) and issubclass(driver, LinuxDriver)
        ):
            return driver
        return _StdoutDriver

    # ------------------------------------------------------------------ layout

    def compose(self) -> ComposeResult:
        yield TextPane(id="header")
        with Horizontal(id="main"):
            with Vertical(id="left"):
                yield MonitorList(id="list")
                yield Details(id="details")
            with Vertical(id="side"):
                yield TextPane(id="robot")
                yield Registers(id="registers")
        yield Input(id="prompt")
        yield Footer()

    def on_mount(self) -> None:
        self.query_one("#list", MonitorList).border_title = "monitor"
        self.query_one("#details", Details).border_title = "details"
        self.query_one("#robot", TextPane).border_title = "robot"
        self.query_one("#registers", TextPane).border_title = "registers"
        self.query_one("#list", MonitorList).focus()
        self._layout()
        if self._first_filter:
            self.set_filter(self._first_filter)
        self.pull()
        self.set_interval(1 / REDRAWS, self.pull)

    def on_resize(self, event: events.Resize) -> None:
        self._layout()

    def _side_wanted(self) -> bool:
        if self.side_forced is not None:
            return self.side_forced
        return self.size.width >= SIDE_FROM

    def _layout(self) -> None:
        """Fold the panes for the terminal's size; styles are set only when they change
        (a change lays the screen out again, which costs more than a redraw)."""
        width, height = self.size
        shown = self._side_wanted()
        wanted = (
            shown,
            46 if width >= SIDE_FROM else max(20, width // 2),
            self.feed.profile or bool(self.snap.state),
            9 if height < 30 else "40%",
        )
        if wanted == self._laid_out:
            return
        self._laid_out = wanted
        side = self.query_one("#side")
        side.set_class(shown, "shown")
        side.styles.width = wanted[1]
        self.query_one("#robot").display = wanted[2]
        self.query_one("#details", Details).styles.height = wanted[3]

    # ------------------------------------------------------------------ data

    def _print(self, text: str, stderr: bool = False) -> None:
        """What anyone prints while the screen runs is kept and shown after it closes."""
        if self.is_headless:
            super()._print(text, stderr)
            return
        with self._captured_lock:
            self.captured.append(text)

    def pull(self) -> None:
        """Copy the feed and redraw, when it changed (at most :data:`REDRAWS` a second)."""
        if self.worker is not None and not self.worker.is_alive():
            if self.stopping or self.signalled:
                self.exit()
                return
        version = self.feed.version
        if version == self._shown_version:
            return
        now = time.monotonic()
        if now - self._drawn_at < 1 / DATA_REDRAWS:
            return  # the next look redraws
        self._drawn_at = now
        self._shown_version = version
        self._take_snapshot()
        self.redraws += 1
        self._draw_header()
        if not self.paused:
            self._show_rows()
        self._draw_side()

    def _take_snapshot(self) -> None:
        """A copy of the feed; the register image's copy is kept while it is unchanged."""
        old = self.snap
        snap = self.feed.snapshot(old.registers_version if old.registers is not None else -1)
        if snap.registers is None:
            snap.registers = old.registers
        self.snap = snap

    def _rows(self) -> list[Entry]:
        entries = self._frozen if self._frozen is not None else self.snap.entries
        if self._filter is None:
            return entries
        first = entries[0].seq if entries else 0
        if self._filtered and self._filtered[0].seq < first:
            self._filtered = self._filtered[bisect.bisect_left([e.seq for e in self._filtered],
                                                               first):]  # fmt: skip
        flt = self._filter
        for e in entries:
            if e.seq > self._filtered_upto and flt.matches_record(e.record, e.line):
                self._filtered.append(e)
        if entries:
            self._filtered_upto = max(self._filtered_upto, entries[-1].seq)
        return self._filtered

    def _show_rows(self) -> None:
        lst = self.query_one("#list", MonitorList)
        before = lst.selected
        lst.set_rows(self._rows())
        after = lst.selected
        details = self.query_one("#details", Details)
        same = before is not None and after is not None and before.seq == after.seq
        details.show(after, self.snap, same=same)
        self._set_list_title()

    def _set_list_title(self) -> None:
        lst = self.query_one("#list", MonitorList)
        shown = len(lst.rows)
        kept = len(self.snap.entries) if self._frozen is None else len(self._frozen)
        title = f"monitor: {shown} lines"
        if self._filter is not None:
            title += f" of {kept} (filter: {self.filter_text})"
        if lst.marks:
            title += f", {len(lst.marks)} marked"
        if title != lst.border_title:
            lst.border_title = title

    def _draw_header(self) -> None:
        """Title, the state (LIVE, PAUSED, ENDED, STOPPING: first, so that a narrow
        screen shows it), rate, counts and the command's figures."""
        snap = self.snap
        text = Text()
        items = header_items(self.feed.title, snap)
        text.append(str(items[0][1]), style="bold")
        text.append(" ")
        if self.stopping:
            text.append(" STOPPING… ", style="bold black on yellow")
        elif snap.ended:
            text.append(" ENDED ", style="bold black on cyan")
        elif self.paused:
            frozen = self._frozen[-1].seq if self._frozen else -1
            text.append(f" PAUSED +{snap.total - 1 - frozen} new ", style="bold black on yellow")
        else:
            text.append(" LIVE ", style="bold black on green")
        for label, value in items[1:]:
            text.append("  ")
            if not label:
                text.append(str(value), style="bold cyan")
                continue
            text.append(f"{label} ")
            bad = (label in ("exceptions", "timeouts", "warnings") and value) or (
                label.endswith("drops") and isinstance(value, int) and value > 0
            )
            text.append(str(value), style="bold red" if bad else "bold")
        if snap.total > len(snap.entries):
            text.append(f"  kept: last {len(snap.entries)}", style="dim")
        if snap.ended and not self.stopping:
            text.append(f"  {self.ended_note}", style="cyan")
        self.query_one("#header", TextPane).set_text(text)

    def _draw_side(self) -> None:
        self._layout()
        if not self._side_wanted():
            return
        snap = self.snap
        if self.query_one("#robot").display:
            robot = (tuple(snap.state.items()), snap.command, tuple(snap.parameters))
            if robot != self._drawn_robot:
                self._drawn_robot = robot
                self.query_one("#robot", TextPane).set_text(robot_text(snap))
        last = snap.entries[-1].record.ts if snap.entries else time.time()
        # redrawn when the image changed, when a highlight may have to go, or on s / d
        key = (snap.registers_version, self.diff, id(self.snapshot_values), int(last))
        if key != self._drawn_registers:
            self._drawn_registers = key
            self.query_one("#registers", TextPane).set_text(
                registers_text(snap.registers or {}, self.snapshot_values, diff=self.diff, now=last)
            )
        pane = self.query_one("#registers", TextPane)
        pane.border_title = "registers: changed since snapshot" if self.diff else "registers"

    def on_monitor_list_moved(self, message: MonitorList.Moved) -> None:
        lst = self.query_one("#list", MonitorList)
        self.query_one("#details", Details).show(lst.selected, self.snap)

    # ------------------------------------------------------------------ actions

    def action_pause(self) -> None:
        self.paused = not self.paused
        if self.paused:
            self._frozen = list(self.snap.entries)
        else:
            self._frozen = None
            self._show_rows()
        self._draw_header()

    def action_ask(self, what: str) -> None:
        prompt = self.query_one("#prompt", Input)
        self._asking = what
        prompt.placeholder = {
            "search": "search: text (any case), enter searches, escape cancels",
            "filter": "filter: --unit N --fc N[,N] --address A[-B] --grep TEXT (empty: none)",
            "write": "write the kept lines (or the marked range) to: FILE.mcap/.jsonl/.csv/"
            ".txt/.pcap",
        }[what]
        prompt.value = {"search": self.search_text, "filter": self.filter_text}.get(what, "")
        prompt.add_class("shown")
        prompt.focus()

    def action_cancel(self) -> None:
        prompt = self.query_one("#prompt", Input)
        if prompt.has_class("shown"):
            prompt.remove_class("shown")
            self._asking = ""
            self.query_one("#list", MonitorList).focus()

    def on_input_submitted(self, message: Input.Submitted) -> None:
        what, value = self._asking, message.value
        self.action_cancel()
        if what == "search":
            self.search(value)
        elif what == "filter":
            self.set_filter(value)
        elif what == "write":
            self.write(value)

    def search(self, text: str) -> None:
        """Find ``text`` (any case, as ``--grep``) from the selected line on."""
        self.search_text = text
        lst = self.query_one("#list", MonitorList)
        lst.query_text = text
        lst.refresh()
        if text:
            self.action_next_match(1, from_here=True)

    def action_next_match(self, step: int, from_here: bool = False) -> None:
        lst = self.query_one("#list", MonitorList)
        needle = self.search_text.lower()
        if not needle:
            self.notify("no search yet: / searches", markup=False)
            return
        rows = lst.rows
        n = len(rows)
        start = lst.cursor if lst.cursor >= 0 else n - 1
        first = 0 if from_here else 1
        for k in range(first, n + first):
            i = (start + step * k) % n if n else 0
            if needle in rows[i].line.lower():
                if (step > 0 and i < start) or (step < 0 and i > start):
                    self.notify("search wrapped around", markup=False)
                lst.select(i, follow=False)
                return
        self.notify(f"not found: {self.search_text}", severity="warning", markup=False)

    def set_filter(self, text: str) -> None:
        """The display filter, in the command-line syntax (empty: none)."""
        try:
            flt = parse_display_filter(text)
        except FilterSyntaxError as exc:
            self.notify(f"filter not set: {exc}", severity="error", markup=False)
            return
        self._filter = flt
        self.filter_text = text.strip() if flt is not None else ""
        self._filtered = []
        self._filtered_upto = -1
        lst = self.query_one("#list", MonitorList)
        lst.set_rows(self._rows())
        self.query_one("#details", Details).show(lst.selected, self.snap)
        self._set_list_title()

    def action_snapshot(self) -> None:
        self._take_snapshot()
        self.snapshot_values = {k: c.value for k, c in (self.snap.registers or {}).items()}
        self.notify(f"snapshot of {len(self.snapshot_values)} registers and coils; "
                    "d shows what changes", markup=False)  # fmt: skip
        self._draw_side()

    def action_diff(self) -> None:
        if self.snapshot_values is None:
            self.notify("no snapshot yet: s takes one", severity="warning", markup=False)
            return
        self.diff = not self.diff
        if self.diff and not self._side_wanted():
            self.side_forced = True
        self._draw_side()

    def action_side(self) -> None:
        self.side_forced = not self._side_wanted()
        self._draw_side()

    def action_mark(self) -> None:
        lst = self.query_one("#list", MonitorList)
        entry = lst.selected
        if entry is None:
            return
        lst.marks.symmetric_difference_update({entry.seq})
        lst.refresh()
        self._set_list_title()

    def action_next_mark(self) -> None:
        lst = self.query_one("#list", MonitorList)
        marks = sorted(s for s in lst.marks if lst.index_of(s) is not None)
        if not marks:
            self.notify("no marks: m marks the selected line", markup=False)
            return
        here = lst.selected.seq if lst.selected is not None else -1
        after = [s for s in marks if s > here]
        target = after[0] if after else marks[0]
        index = lst.index_of(target)
        if index is not None:
            lst.select(index, follow=False)

    def marked_range(self) -> list[Entry]:
        """What ``w`` writes: the kept lines shown, or from the first to the last mark."""
        lst = self.query_one("#list", MonitorList)
        rows = lst.rows
        marks = sorted(lst.marks)
        if len(marks) >= 2:
            return [e for e in rows if marks[0] <= e.seq <= marks[-1]]
        return list(rows)

    def write(self, path: str) -> None:
        path = path.strip()
        if not path:
            return
        if self._save is None:
            self.notify("this screen cannot write files", severity="error", markup=False)
            return
        entries = self.marked_range()
        try:
            said = self._save(path, entries)
        except Exception as exc:  # a bad path or format: said, and the screen goes on
            self.notify(f"not written: {exc}", severity="error", markup=False)
            return
        self.notify(said, markup=False)

    def action_help(self) -> None:
        self.push_screen(HelpScreen())

    def action_stop(self) -> None:
        """q / ctrl+c: stop the run; the screen closes once the logs are finished."""
        if self.worker is None or not self.worker.is_alive():
            self.exit()
            return
        if not self.stopping:
            self.stopping = True
            self._draw_header()
            if self._stop is not None:
                self._stop()

    # ------------------------------------------------------------------ tests and docs

    def screen_text(self) -> str:
        """The screen as plain text, as a terminal shows it (docs' text captures, tests)."""
        import io

        from rich.console import Console

        width, height = self.size
        console = Console(width=width, height=height, file=io.StringIO(), record=True,
                          color_system=None, legacy_windows=False, safe_box=False)  # fmt: skip
        update = self.screen._compositor.render_update(
            full=True, screen_stack=self._background_screens
        )
        console.print(update)
        return console.export_text()


def render_text(
    feed: MonitorFeed, size: tuple[int, int] = (160, 50), keys: tuple[str, ...] = ()
) -> str:
    """The screen showing ``feed``, drawn headless at ``size`` after pressing ``keys``,
    as plain text (the docs' captures; tests of what a terminal would show)."""
    import asyncio

    async def draw() -> str:
        app = MonitorApp(feed)
        async with app.run_test(size=size) as pilot:
            await pilot.pause()
            for key in keys:
                await pilot.press(key)
            await pilot.pause(0.2)
            return app.screen_text()

    return asyncio.run(draw())
