"""The monitor's side column: the robot panel (axes, speed, motion state, the last
command) and the register image, with recent changes highlighted.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

from rich.text import Text
from textual.binding import Binding

from mbmon.monitor.feed import Cell, FeedView, register_name
from mbmon.monitor.widgets import TextPane

#: A register changed within this many seconds (of the traffic's time) is highlighted.
CHANGED_FOR = 2.0


def _time_text() -> Callable[[float], str]:
    """Times of day for the side panes, from a time format of the screen's own: the
    one format.format_time uses keeps a per-second cache the hub's thread writes."""
    from mbmon.timefmt import TimeFormat

    return TimeFormat(auto_date=False).text


format_time = _time_text()

_PHASE_STYLE = {"success": "green", "fail": "bold red", "warning": "yellow"}
_STATE_CELLS = (
    ("A1", "a1"), ("A2", "a2"), ("A3", "a3"), ("A4", "a4"), ("A5", "a5"), ("A6", "a6"),
    ("X", "x"), ("Y", "y"), ("Z", "z"), ("A", "a"), ("B", "b"), ("C", "c"),
)  # fmt: skip


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
