"""The monitor's widgets: the monitor list (:class:`MonitorList`, the lines ``read``
prints, drawn row by row), a pane of text that scrolls by lines (:class:`TextPane`,
the base of the details and register panes) and the help screen (:data:`HELP`).
Every text from the wire is a :class:`rich.text.Text` (never markup).
"""

from __future__ import annotations

import bisect
from typing import Any, ClassVar

from rich.segment import Segment
from rich.style import Style
from rich.text import Text
from textual import events
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import VerticalScroll
from textual.screen import ModalScreen
from textual.strip import Strip
from textual.widget import Widget
from textual.widgets import Static

from mbmon.model import RecordKind
from mbmon.monitor.feed import Entry

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
