"""What a command shows on the terminal: the console or the live monitor, figures for
it, the display filter it starts with, and a progress bar for long reads.

Re-exported by :mod:`mbmon.commands.common`. Records go to stdout, progress and
messages to stderr.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any


class Progress:
    """A rich progress bar on stderr for long work, only when stderr is a terminal.

    It never takes stdout: records go to stdout, progress to stderr.
    """

    MIN_BYTES = 4 << 20  # about a second of reading

    def __init__(self, label: str, enabled: bool | None = None):
        self._bar: Any = None
        self._task: Any = None
        self._label = label
        self._enabled = sys.stderr.isatty() if enabled is None else enabled

    def __call__(self, done: int, total: int) -> None:
        if not self._enabled or total < self.MIN_BYTES:
            return
        if self._bar is None:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                DownloadColumn,
                Progress,
                TextColumn,
                TimeRemainingColumn,
            )

            self._bar = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                DownloadColumn(),
                TimeRemainingColumn(),
                console=Console(stderr=True),
                transient=True,
                redirect_stdout=False,
                redirect_stderr=False,
            )
            self._bar.start()
            self._task = self._bar.add_task(self._label, total=total)
        self._bar.update(self._task, completed=done)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


def wants_state_panel(annotator: Any) -> bool:
    """Whether the live monitor shows the state panel: the run's annotator (``None``
    without ``--profile``) has a profile that names a device session
    (:attr:`~mbmon.semantics.annotate.Annotator.has_sessions`): the annotator
    decides, not the spelling of ``--profile`` (a copy of the HRSS map in a file of
    any name gets the panel; a file in an ``hrss`` folder without a session does not)."""
    return bool(annotator is not None and annotator.has_sessions)


class Figures:
    """A hub listener that feeds a command's own figures (kernel drops, bus health,
    proxy clients and refusals) to the live monitor on every tick.

    ``source()`` returns the figures (name -> value); it runs in the hub's thread.
    """

    name = "figures"

    def __init__(self, monitor: Any, source: Any) -> None:
        self.monitor = monitor
        self.source = source

    def on_tick(self, now: float) -> None:
        self.monitor.set_figures(self.source())


def open_console(
    args: argparse.Namespace, view: Any, *, title: str, annotator: Any = None
) -> tuple[Any, Any]:
    """The one place a live command decides what goes to the terminal.

    Returns ``(listener, monitor)``: nothing with ``-q``; plain lines
    (:class:`~mbmon.sinks.console.ConsoleListener`) with ``--json``, ``--plain`` or
    when stdout or stdin is not a terminal; otherwise the interactive monitor's feed
    (:class:`~mbmon.monitor.feed.MonitorFeed`), which is then both the listener and
    the monitor (for figures a command feeds it, and for :func:`run_live`). With the
    run's ``annotator``, the robot panel shows the HRSS sessions' written parameter
    registers (R200..R251).
    """
    if args.quiet:
        return None, None
    if args.json or getattr(args, "plain", False) or not _interactive():
        from mbmon.sinks.console import ConsoleListener

        return ConsoleListener(sys.stdout, view, as_json=args.json, live=True), None
    from mbmon.monitor.feed import MonitorFeed

    monitor = MonitorFeed(
        view, title=title, profile=wants_state_panel(annotator), annotator=annotator
    )
    return monitor, monitor


def _interactive() -> bool:
    """Whether the screen can run: stdout is a terminal, and so is stdin (its keys)."""
    try:
        return sys.stdout.isatty() and sys.stdin is not None and sys.stdin.isatty()
    except (AttributeError, ValueError):
        return False


def filter_text(args: argparse.Namespace) -> str:
    """The command-line filters (``--unit --fc --address --since --until --grep``) as
    the monitor's display filter, in the same syntax (``f`` on the screen edits it)."""
    import shlex

    parts: list[str] = []
    for unit in getattr(args, "unit", None) or []:
        parts += ["--unit", unit]
    for fc in getattr(args, "fc", None) or []:
        parts += ["--fc", fc]
    for name in ("address", "since", "until", "grep"):
        value = getattr(args, name, None)
        if value:
            parts += [f"--{name}", value]
    return shlex.join(parts)


def run_live(monitor: Any, work: Any, stop: Any, **screen: Any) -> None:
    """Run ``work`` (a live command's hub loop): here without a monitor, else in a thread
    of its own under the interactive screen (:func:`mbmon.monitor.run_screen`, which
    takes ``screen``'s keywords), which ``stop`` ends as Ctrl-C would."""
    if monitor is None:
        work()
        return
    from mbmon.monitor import run_screen

    run_screen(monitor, work, stop, **screen)
