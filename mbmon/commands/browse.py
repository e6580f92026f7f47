"""``mbmon replay --browse``: a log in the interactive monitor, decoded again through
the one flow."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from typing import Any

from mbmon.commands.common import EXIT_BAD_INPUT, EXIT_OK, EXIT_USAGE
from mbmon.commands.logfile import err, log_times, note_status, open_log, replay_view

#: Records ``replay --browse`` keeps (the live monitor keeps the last 10,000).
BROWSE_KEEP = 200_000


def run_browse(args: argparse.Namespace) -> int:
    """``mbmon replay --browse``: the log in the interactive monitor, its raw bytes
    decoded again through the one flow (as ``--redecode``: the lines ``read`` prints),
    the command-line filters as the screen's first display filter."""
    from mbmon.commands.common import filter_text, wants_state_panel
    from mbmon.filters import FilterError
    from mbmon.hub import Hub
    from mbmon.io.mcap.layout import METADATA_NAME, TOPIC_RAW
    from mbmon.io.mcap.reader import LogError
    from mbmon.io.replay import raw_items, recorded_annotator, recorded_options
    from mbmon.monitor import run_screen
    from mbmon.monitor.feed import MonitorFeed
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sinks.base import SinkContext

    if args.json or args.speed or getattr(args, "foxglove", None) is not None:
        err("error: --browse shows the log on the screen: no --json, --speed or --foxglove")
        return EXIT_USAGE
    if not (sys.stdout.isatty() and sys.stdin.isatty()):
        err("error: --browse needs a terminal (stdin and stdout); without one, replay prints")
        return EXIT_USAGE
    log, status = open_log(args.log, "replay")
    if log is None:
        return status
    with log:
        if TOPIC_RAW not in log.topics:
            err(f"error: {args.log} has no {TOPIC_RAW} (raw bytes) to browse; "
                 "mbmon replay prints its stored lines")  # fmt: skip
            return EXIT_BAD_INPUT
        try:
            fmt, _flt = log_times(args, log)
            opts = recorded_options(log)
            annotator = recorded_annotator(log, opts)
        except (FilterError, LogError) as exc:
            err(f"error: {exc}")
            return EXIT_USAGE if isinstance(exc, FilterError) else EXIT_BAD_INPUT
        view = replay_view(log, args, fmt)
        feed = MonitorFeed(
            view,
            title=f"mbmon replay {log.path.name}",
            keep=BROWSE_KEEP,
            annotator=annotator,
            profile=wants_state_panel(annotator),
        )
        pipeline = Pipeline(annotator, PipelineConfig(timeout=opts.timeout, baudrate=opts.baud))
        hub = Hub(pipeline, [feed])
        ctx = SinkContext(
            view=view,
            command_line=["mbmon", *sys.argv[1:]],
            source=log.metadata.get(METADATA_NAME, {}).get("source", str(log.path)),
            profiles=log.profiles(),
            profile_specs=opts.profile_specs,
            timeout=opts.timeout,
            baud=opts.baud,
        )
        failed: list[str] = []

        def work() -> None:
            try:
                hub.run_items(_browse_items(log, raw_items, lambda: hub.records))
            except LogError as exc:
                failed.append(str(exc))
            hub.tick(hub.now)  # the run's end: the rate and the robot panel's registers
            hub.close()

        run_screen(
            feed,
            work,
            hub.enough,
            ctx=ctx,
            ended_note="end of the log; q quits",
            display_filter=filter_text(args),
        )
        for message in failed:
            err(message)
        note_status(log)
    return EXIT_BAD_INPUT if failed else EXIT_OK


#: Events a log holds only as records (not on /modbus/raw): ``--browse`` feeds them
#: again, in their place, so its list has the lines ``replay`` prints.
_RECORD_ONLY_EVENTS = ("notice", "guard")


def _browse_items(log: Any, raw_items: Any, made: Any) -> Iterator[Any]:
    """The log's raw chunks and source events, with its notices and guard decisions
    (kept only as records) fed again where the recording had them: before the raw
    item that made the record of the same number (``made()``: records made so far)."""
    from collections import deque

    from mbmon.io.replay import logged_records
    from mbmon.model import Event, EventKind

    stored = deque(
        (int(r.obj.get("index") or 0),
         Event(r.time, None, EventKind(r.obj["event"]), dict(r.obj.get("info") or {})))
        for r in logged_records(log)
        if r.obj is not None
        and r.obj.get("kind") == "event"
        and r.obj.get("event") in _RECORD_ONLY_EVENTS
    )  # fmt: skip
    for item in raw_items(log):
        while stored and stored[0][0] <= made():
            yield stored.popleft()[1]
        yield item
    for _index, event in stored:
        yield event
