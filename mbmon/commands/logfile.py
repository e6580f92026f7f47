"""What the log commands (``replay``, ``info``, ``export``) share: opening a log with one
clear line when it cannot be read, its time format and filter, the progress bar, and
the report of what damage left out.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from mbmon.commands.common import EXIT_BAD_INPUT, EXIT_OK, EXIT_USAGE


def err(message: str) -> None:
    print(f"mbmon: {message}", file=sys.stderr)


#: first bytes of packet captures: pcap (both byte orders, us and ns) and pcapng
_CAPTURE_MAGICS = (b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\xc3\xd4", b"\x4d\x3c\xb2\xa1",
                   b"\xa1\xb2\x3c\x4d", b"\x0a\x0d\x0d\x0a")  # fmt: skip


def is_capture(path: str | Path) -> bool:
    """Whether ``path`` starts like a pcap or pcapng file (what ``mbmon read`` takes)."""
    try:
        with open(path, "rb") as f:
            return f.read(4) in _CAPTURE_MAGICS
    except OSError:
        return False


def open_log(path: str, command: str) -> tuple[Any, int]:
    """The log at ``path`` and 0, or ``None`` and the exit status after saying, in one
    line, why it cannot be read (a packet capture: exit 2 and ``mbmon read`` suggested)."""
    from mbmon.io.mcap.reader import LogError, McapLog

    try:
        return McapLog(path), EXIT_OK
    except LogError as exc:
        if is_capture(path):
            err(f"error: {path} is a packet capture, not an MCAP log: "
                 f"use 'mbmon read {path}' (add -w LOG.mcap to record one)")  # fmt: skip
            return None, EXIT_USAGE
        text = str(exc)
        if "not an MCAP file" in text:
            text += f"; {command} reads the MCAP logs written by 'mbmon read ... -w LOG.mcap'"
        err(text)
        return None, EXIT_BAD_INPUT


def progress(log: Any) -> Any:
    """A progress bar on stderr for a big log, when stderr is a terminal (never stdout's):
    the one ``read`` shows for big captures, fed by the reader after every chunk."""
    from mbmon.commands.common import Progress

    bar = Progress(f"reading {log.path.name}")
    log.progress = bar
    return bar


def log_times(args: argparse.Namespace, log: Any) -> tuple[Any, Any]:
    """The log's time format (``-t``, origin and date rule from its span) and filter."""
    from mbmon.filters import build_filter
    from mbmon.io.replay import first_record_time
    from mbmon.timefmt import TimeFormat

    start = first_record_time(log)
    # the rule `read` prints by while streaming (a date on times of another day than
    # the first record's), so replayed lines are the lines read printed
    fmt = TimeFormat(getattr(args, "time_format", "a"), origin=start)
    return fmt, build_filter(args, start, fmt)


def filter_failed(log: Any, exc: Exception) -> int:
    """A filter that cannot be built: a usage error (2), unless no record of the log can
    be read because of damage (``--since +5s`` has no start): then the damage (1)."""
    status = log.status
    if status.stopped_at is not None and "no records" in str(exc):
        err(f"{log.path}: no record can be read: {status.problem} (at byte {status.stopped_at})")
        return EXIT_BAD_INPUT
    err(f"error: {exc}")
    return EXIT_USAGE


def retimed(
    obj: dict[str, Any] | None, line: str, ts: float, fmt: Any
) -> tuple[dict[str, Any] | None, str]:
    """A logged record's object and line with the line's time printed in ``fmt``."""
    from mbmon.timefmt import replace_time

    new = replace_time(line, fmt.text(ts))
    if new == line:
        return obj, line
    if obj is not None and obj.get("line") == line:
        obj = {**obj, "line": new}
    return obj, new


def note_status(log: Any) -> None:
    status = log.status
    if not status.finished:
        err(f"note: {log.path}: {status.describe()}")


def report_skipped(log: Any) -> bool:
    """Say which damaged messages the reading left out (stderr); whether there were any."""
    lines = log.status.skipped_lines()
    if lines:
        err(f"{log.path}: {lines[0]}")
        for line in lines[1:]:
            print(line, file=sys.stderr)
    return bool(lines)


def replay_view(log: Any, args: argparse.Namespace, fmt: Any = None) -> Any:
    """The view of a re-decode: ``--robot`` if given, else the recording's."""
    from mbmon.format import View
    from mbmon.io.replay import recorded_options

    opts = recorded_options(log)
    robot, is_client = (
        (args.robot, args.robot_client) if args.robot else (opts.robot, opts.robot_is_client)
    )
    if fmt is None:
        return View(robot=robot, robot_is_client=is_client)
    return View(robot=robot, robot_is_client=is_client, time_format=fmt)
