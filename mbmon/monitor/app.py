"""The interactive monitor's screen, on textual (imported only when a monitor runs).

:class:`MonitorApp` shows a :class:`~mbmon.monitor.feed.MonitorFeed`: a header
with counts and rates, the monitor list (the lines ``read`` prints, newest at
the bottom), a details pane for the selected line (the fields ``decode``
prints, from :func:`mbmon.details.frame_details`, the paired request or
answer, latency, notes, the raw bytes with the field under the cursor
highlighted), and, when there is room or on ``r``, the robot panel and the
register image. Keys are listed in :data:`mbmon.monitor.widgets.HELP` (``?`` on the
screen). The widgets are :mod:`~mbmon.monitor.widgets`, the details pane
:mod:`~mbmon.monitor.details`, the side column :mod:`~mbmon.monitor.side`; this
module lays them out and keeps them in step with the feed.

The screen never drives the capture: it looks at the feed :data:`REDRAWS`
times a second and copies and redraws it, when something changed, at most
:data:`DATA_REDRAWS` times a second (keys are answered at once). The lines come
made from the hub's thread; the details are made here from the kept records
(format's text caches are dicts: two threads at worst compute a text twice).
Every text from the wire is a :class:`rich.text.Text` (never markup), so
untrusted bytes cannot style the screen.
"""

from __future__ import annotations

import bisect
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

from rich.text import Text
from textual import events
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Footer, Input

from mbmon.monitor.details import Details
from mbmon.monitor.display_filter import FilterSyntaxError, parse_display_filter
from mbmon.monitor.feed import Entry, FeedView, MonitorFeed, header_items
from mbmon.monitor.side import Registers, registers_text, robot_text
from mbmon.monitor.widgets import HelpScreen, MonitorList, TextPane

#: The screen looks at the feed this many times a second (and answers keys at once);
REDRAWS = 10
#: but redraws for new traffic at most this many times a second: a redraw moves every
#: row of the list, and nobody reads faster (at 5,000 frames/s it keeps the screen
#: under 10 % of a core: bench/monitor_load.py)
DATA_REDRAWS = 4
#: The side column (robot panel, register image) shows by itself from this width on.
SIDE_FROM = 120


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
