"""The live monitor: a rich screen like the robot's Modbus Monitor, as a hub listener.

:class:`LiveMonitor` keeps the last :data:`LINES` monitor lines (made by
:func:`mbmon.format.record_line`, notes included), counts and rates, and with an
HRSS profile the robot state (A1..A6, X..C, speed, motion state), the last
reconstructed command with its outcome, and the register image of the command
parameters R200..R251 as the client wrote them, each named as the HRSS command
spec names it for the command in R201 (:func:`parameter_rows`; the image is the
annotator's HRSS session's, read in the hub's thread). It draws a header with
the figures, the state panel when there is state, and a pane with as many of
the newest lines as the terminal has room for. Any command can use it (``sniff``, later ``proxy``,
``demo``, ``replay --speed``); a command adds its own figures (kernel drops,
bus health) with :meth:`LiveMonitor.set_figure`.

Every text from the wire (monitor lines, notes, command texts, endpoint names)
becomes a :class:`rich.text.Text`, never markup, so untrusted bytes cannot
style or break the screen. The screen is redrawn from the hub's thread in
``on_tick`` (no refresh thread touches the state), and rich's ``Live`` does not
take over stdout or stderr of anyone else (``redirect_stdout=False``).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Mapping
from typing import Any

from mbmon.format import View, format_time, record_line
from mbmon.model import EventKind, Record, RecordKind

__all__ = ["LINES", "LiveMonitor", "parameter_rows"]

#: Monitor lines kept for the scrolling pane.
LINES = 200
#: Seconds over which frames/s is computed.
RATE_WINDOW = 2.0

_STATE_ROWS: tuple[tuple[tuple[str, str], ...], ...] = (
    (("A1", "a1"), ("A2", "a2"), ("A3", "a3"), ("A4", "a4"), ("A5", "a5"), ("A6", "a6")),
    (("X", "x"), ("Y", "y"), ("Z", "z"), ("A", "a"), ("B", "b"), ("C", "c")),
)
_STYLE = {
    RecordKind.REQUEST: "",
    RecordKind.RESPONSE: "green",
    RecordKind.EXCEPTION: "bold red",
    RecordKind.NOISE: "yellow",
    RecordKind.EVENT: "cyan",
    RecordKind.COMMAND: "magenta",
}
_PHASE_STYLE = {"success": "green", "fail": "bold red", "warning": "yellow"}


class LiveMonitor:
    """A hub listener that draws the live screen (see the module text)."""

    name = "live monitor"

    def __init__(
        self,
        view: View,
        console: Any = None,
        *,
        title: str = "mbmon",
        lines: int = LINES,
        state_panel: bool = False,
        start: bool = True,
        clock: Any = time.time,
        annotator: Any = None,
    ) -> None:
        from rich.console import Console

        self.view = view
        self.console = console if console is not None else Console()
        self.title = title
        self.lines: deque[Any] = deque(maxlen=lines)
        self.state_panel = state_panel
        self._clock = clock
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
        #: the annotator's HRSS sessions by (server, unit): the written register image
        self._sessions: Any = getattr(annotator, "sessions", None)
        self._robot: tuple[str, int] | None = None  # the session of the last command/state
        self.rate = 0.0
        self._samples: deque[tuple[float, int]] = deque()
        self._live: Any = None
        if start:
            from rich.live import Live

            self._live = Live(
                self.render(),
                console=self.console,
                auto_refresh=False,
                transient=False,
                redirect_stdout=False,
                redirect_stderr=False,
            )
            self._live.start()

    # ------------------------------------------------------------------ hooks

    def on_records(self, records: list[Record]) -> None:
        from rich.text import Text

        counts = self.counts
        view = self.view
        for record in records:
            kind = record.kind
            if record.frame is not None:
                counts["frames"] += 1
                if kind is RecordKind.REQUEST:
                    counts["requests"] += 1
                elif kind is RecordKind.RESPONSE:
                    counts["responses"] += 1
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
                if record.frame is not None:
                    self._robot = (record.frame.stream.server, record.frame.unit)
            self.lines.append(Text(record_line(record, view), style=_STYLE.get(kind, "")))

    def on_tick(self, now: float) -> None:
        self._update_rate(now)
        self.refresh()

    def close(self) -> None:
        if self._live is not None:
            self.refresh()
            self._live.stop()
            self._live = None

    # ------------------------------------------------------------------ for commands

    def set_figure(self, name: str, value: Any) -> None:
        """A figure of the command's own shown in the header (e.g. ``kernel drops``).

        ``open connections`` replaces the monitor's own count (connects minus
        disconnects seen), which misses connections opened before the capture
        began: a source that knows its open connections (the packet dissector)
        gives the true figure."""
        self.figures[name] = value

    def set_figures(self, figures: Mapping[str, Any]) -> None:
        self.figures.update(figures)

    def refresh(self) -> None:
        if self._live is not None:
            self._live.update(self.render(), refresh=True)

    # ------------------------------------------------------------------ drawing

    def _update_rate(self, now: float) -> None:
        samples = self._samples
        samples.append((now, self.counts["frames"]))
        while len(samples) > 2 and now - samples[0][0] > RATE_WINDOW:
            samples.popleft()
        t0, n0 = samples[0]
        self.rate = (self.counts["frames"] - n0) / (now - t0) if now > t0 else 0.0

    def render(self) -> Any:
        """The whole screen as one renderable (also what tests print to a recording console)."""
        from rich.console import Group
        from rich.panel import Panel
        from rich.text import Text

        parts: list[Any] = [self._header()]
        used = 3 + 2
        if self.state_panel or self.state or self.command is not None:
            parts.append(self._state())
            used += 6
            rows = parameter_rows(*self._written())
            if rows:
                parts.append(self._parameters(rows))
                used += 2 + -(-len(rows) // _PARAM_COLUMNS)
        height = self.console.size.height
        room = max(3, height - used)
        shown = list(self.lines)[-room:]
        # one row per record: long lines end in "…" instead of wrapping off the screen
        newline = Text("\n", no_wrap=True, overflow="ellipsis")
        body = newline.join(shown) if shown else Text("waiting for traffic…", style="dim")
        parts.append(Panel(body, title="monitor", title_align="left", border_style="dim"))
        return Group(*parts)

    def _header(self) -> Any:
        from rich.text import Text

        c = self.counts
        text = Text()
        text.append(self.title, style="bold")
        text.append(f"  {self.rate:.1f} frames/s", style="bold cyan")
        pieces = [
            ("frames", c["frames"], ""),
            ("requests", c["requests"], ""),
            ("responses", c["responses"], ""),
            ("exceptions", c["exceptions"], "red" if c["exceptions"] else ""),
            ("timeouts", c["timeouts"], "red" if c["timeouts"] else ""),
            ("noise bytes", c["noise_bytes"], "yellow" if c["noise_bytes"] else ""),
            ("open connections", self.figures.get("open connections", c["open_connections"]), ""),
        ]
        for label, value, style in pieces:
            text.append(f"  {label} ")
            text.append(str(value), style=style or "bold")
        for label, value in self.figures.items():
            if label == "open connections":
                continue  # shown in its place above
            text.append(f"  {label} ")
            bad = label == "warnings" or (
                label.endswith("drops") and isinstance(value, int) and value > 0
            )
            text.append(str(value), style="bold red" if bad else "bold")
        return text

    def _state(self) -> Any:
        from rich.panel import Panel
        from rich.table import Table
        from rich.text import Text

        state = self.state
        table = Table.grid(padding=(0, 2))
        for _ in range(6):
            table.add_column(justify="right")
        for row in _STATE_ROWS:
            cells = []
            for label, key in row:
                value = state.get(key)
                cells.append(Text(f"{label} {value:9.3f}" if value is not None else f"{label}   —"))
            table.add_row(*cells)
        extra = Text()
        for label, key, fmt in (
            ("speed", "speed_pct", "{:.0f} %"),
            ("motion state", "motion_state", "{:.0f}"),
            ("TCP speed", "tcp_speed", "{:.1f}"),
        ):
            value = state.get(key)
            extra.append(f"{label} ")
            extra.append(fmt.format(value) if value is not None else "—", style="bold")
            extra.append("   ")
        cmd = self.command
        last = Text("last command")
        if cmd is not None:
            last.append(f" ({format_time(cmd.ts)})", style="dim")
        last.append(": ")
        if cmd is None:
            last.append("—", style="dim")
        else:
            phase = cmd.phase.value
            last.append(str(cmd.text))
            last.append(f"  [{phase}", style=_PHASE_STYLE.get(phase, "bold"))
            if cmd.duration is not None:
                last.append(f" after {cmd.duration:.3f} s", style=_PHASE_STYLE.get(phase, "bold"))
            last.append("]", style=_PHASE_STYLE.get(phase, "bold"))
        from rich.console import Group

        return Panel(Group(table, extra, last), title="robot", title_align="left")

    def _written(self) -> tuple[Mapping[int, int], frozenset[int]]:
        """The holding image and unconfirmed registers of the robot shown (empty without)."""
        if self._sessions is None:
            return {}, frozenset()
        sessions = self._sessions()
        session = sessions.get(self._robot) if self._robot is not None else None
        if session is None and len(sessions) == 1:
            session = next(iter(sessions.values()))
        if session is None:
            return {}, frozenset()
        return session.holding, session.unconfirmed

    def _parameters(self, rows: list[tuple[str, str, str, bool]]) -> Any:
        from rich.panel import Panel
        from rich.table import Table
        from rich.text import Text

        table = Table.grid(padding=(0, 3))
        for _ in range(_PARAM_COLUMNS):
            table.add_column()
        cells = []
        for regs, name, value, confirmed in rows:
            cell = Text(f"{regs} ", style="dim")
            if name:
                cell.append(f"{name} ", style="bold")
            cell.append(value, style="" if confirmed else "yellow")
            if not confirmed:
                cell.append(" ?", style="yellow")
            cells.append(cell)
        for i in range(0, len(cells), _PARAM_COLUMNS):
            row = cells[i : i + _PARAM_COLUMNS]
            table.add_row(*row, *([Text("")] * (_PARAM_COLUMNS - len(row))))
        return Panel(
            table,
            title="command registers R200..R251 as written (? = write not answered yet)",
            title_align="left",
            border_style="dim",
        )


#: parameter cells per row of the parameters panel
_PARAM_COLUMNS = 4


def parameter_rows(
    holding: Mapping[int, int], unconfirmed: frozenset[int] = frozenset()
) -> list[tuple[str, str, str, bool]]:
    """The written command registers R200..R251 as ``(registers, name, value, confirmed)``.

    Names and values come from the HRSS command spec (``hrss_commands.toml``):
    the execute and command registers by their protocol keys, R202..R251 by
    the fields of the layout the command in R201 (and its select register)
    picks, one row per field (``R203..R204 A1 90 deg``); written registers no
    field names show their unsigned word. ``holding`` is a session's holding
    image (unsigned words); ``unconfirmed`` those whose write is unanswered.
    """
    from mbmon.semantics.hrss.render import decode_command, format_scaled
    from mbmon.semantics.hrss.spec import load_spec
    from mbmon.semantics.words import s16

    spec = load_spec()
    execute, command = spec.reg("execute_reg"), spec.reg("command_reg")
    first, last = min(execute, command), spec.reg("param_last")
    written = {a: v for a, v in holding.items() if first <= a <= last}
    if not written:
        return []
    rows: list[tuple[str, str, str, bool]] = []
    shown: set[int] = set()
    names = {v: k.removesuffix("_reg") for k, v in spec.protocol.items() if k in (
        "execute_reg", "command_reg")}  # fmt: skip

    if execute in written:
        value = s16(written[execute])
        rows.append((f"R{execute}", names[execute], spec.label("execute", value),
                     execute not in unconfirmed))  # fmt: skip
        shown.add(execute)
    decoded = decode_command(written, spec)
    if command in written:
        text = f"{decoded.name} ({decoded.code})" if decoded.code is not None else decoded.name
        rows.append((f"R{command}", names[command], text, command not in unconfirmed))
        shown.add(command)
    fields = []
    cmd = spec.commands.get(decoded.code) if decoded.code is not None else None
    if cmd is not None and cmd.params.select is not None:
        fields.append(cmd.params.select)
    if decoded.layout is not None:
        fields.extend(decoded.layout.fields)
    for f in fields:
        raw = f.raw(written.get)
        if raw is None or f.reg in shown:
            continue
        if f.enum is not None:
            text = spec.label(f.enum, raw)
        elif f.scale != 1 and f.decimals and abs(f.scale - 10.0**-f.decimals) < 1e-12:
            text = format_scaled(raw, f.decimals)
        else:
            text = f"{f.value(raw):g}"
        if f.unit and "|" not in f.unit:
            text += f" {f.unit}" if f.unit != "%" else "%"
        rows.append((f.where(), f.label or f.name, text, not (set(f.regs) & unconfirmed)))
        shown.update(f.regs)
    for address in sorted(set(written) - shown):
        rows.append((f"R{address}", "", str(written[address]), address not in unconfirmed))
    return rows
