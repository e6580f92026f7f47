"""``mbmon replay``: a recorded MCAP log printed as the monitor showed it live (or its
``--json`` objects, or a re-decode), filtered and paced; ``--browse`` in the monitor;
``--serve``/``--to`` against servers (:mod:`mbmon.commands.replay_servers`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from typing import Any

from mbmon.commands import replay_servers
from mbmon.commands.common import (
    EXIT_BAD_INPUT,
    EXIT_OK,
    EXIT_USAGE,
    UsageError,
    add_foxglove_option,
)
from mbmon.commands.logfile import (
    err,
    filter_failed,
    log_times,
    note_status,
    open_log,
    progress,
    report_skipped,
    retimed,
)
from mbmon.filters import add_filter_options
from mbmon.io.livefeed import ReplayFeed
from mbmon.timefmt import add_time_option

EPILOG = """\
examples:
  mbmon replay cell.mcap                      the monitor lines exactly as shown live
  mbmon replay cell.mcap --fc 3,16 --address 200-251
      only Read Holding / Write Multiple Registers touching R200..R251
  mbmon replay cell.mcap --since +30s --until +45s --grep PTP
  mbmon replay cell.mcap --json > frames.jsonl     the same JSON lines as read --json
  mbmon replay cell.mcap --redecode           decode /modbus/raw again with today's decoder
                                              and the profiles stored in the log
  mbmon replay cell.mcap --speed 1            at the original pace (2 = twice as fast)
  mbmon replay cell.mcap --speed 1 --foxglove also live in Foxglove (ws://127.0.0.1:8765)
  mbmon replay cell.mcap --browse             browse it in the interactive monitor

times: +5s / +1m30s / +250ms / 2.5 from the start of the log, 12:00:05.123456 (time of
day on the log's first day), 2024-05-01 12:00:05 (ISO 8601, local time unless it says
otherwise; UTC with -t u/ud), or epoch seconds: every form -t prints. --since and
--until are inclusive.
exit status: 0 ok (also for an unfinished log: a note says how much was recovered),
1 unreadable or damaged log (everything before the damage is printed), 2 usage
"""


def register(sub: Any) -> None:
    """Add ``replay`` to the CLI's sub-parsers."""
    fmt = argparse.RawDescriptionHelpFormatter

    replay = sub.add_parser(
        "replay",
        help="print a recorded MCAP log as the monitor showed it live (with filters)",
        description="Print the monitor lines of an MCAP log written with -w FILE.mcap, "
        "exactly as they were shown live, or the read --json objects; optionally "
        "filtered, re-decoded from the raw bytes, or paced like the original.",
        epilog=EPILOG + "\n" + replay_servers.EPILOG,
        formatter_class=fmt,
    )
    replay.add_argument("log", metavar="LOG.mcap", help="an MCAP log written by mbmon")
    add_filter_options(replay)
    out = replay.add_argument_group("output")
    out.add_argument(
        "--json", action="store_true", help="one read --json object per line (docs/json.md)"
    )
    out.add_argument(
        "--redecode",
        action="store_true",
        help="decode /modbus/raw again with the current decoder and the profiles stored "
        "in the log, instead of printing the stored lines",
    )
    out.add_argument(
        "--robot",
        metavar="HOST[:PORT]",
        help="with --redecode: label lines from this robot's point of view (default: as recorded)",
    )
    out.add_argument(
        "--robot-client",
        action="store_true",
        help="with --redecode, on an RTU bus: the robot named by --robot is the master",
    )
    add_time_option(out)
    out.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="print no lines: the log is still read whole (notes and the exit status say "
        "whether it is damaged or unfinished); use with --foxglove, or to check a log",
    )
    out.add_argument(
        "--speed",
        type=_speed,
        metavar="X",
        help="pace the output like the original: 1 = real time, 10 = ten times faster",
    )
    add_foxglove_option(out)
    out.add_argument(
        "--browse",
        action="store_true",
        help="browse the log in the interactive monitor (search, filter, details, marks); "
        "its raw bytes decoded again as --redecode does",
    )
    replay_servers.add_options(replay)
    replay.set_defaults(func=run_replay)


def _speed(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text}")
    return value


def run_replay(args: argparse.Namespace) -> int:
    """``mbmon replay``: stored lines (or --json objects, or a re-decode), filtered and paced."""
    from mbmon.filters import FilterError, Pacer
    from mbmon.io.mcap.reader import LogError
    from mbmon.sinks.base import SinkError
    from mbmon.sinks.jsonl import dumps_line

    if replay_servers.wanted(args):  # against servers: emulate (--serve) or re-send (--to)
        if args.quiet:
            err("error: -q silences the printed log; --serve and --to print only their report")
            return EXIT_USAGE
        return replay_servers.run(args, open_log, log_times)
    try:
        replay_servers.check_without_mode(args)
    except UsageError as exc:
        err(f"error: {exc}")
        return EXIT_USAGE
    if getattr(args, "browse", False):
        return run_browse(args)
    if (args.robot or args.robot_client) and not args.redecode:
        err("error: --robot relabels lines only with --redecode (stored lines are as recorded)")
        return EXIT_USAGE
    log, status = open_log(args.log, "replay")
    if log is None:
        return status
    out = sys.stdout
    bar = progress(log)
    with log:
        try:
            fmt, flt = log_times(args, log)
        except FilterError as exc:
            return filter_failed(log, exc)
        pacer = Pacer(args.speed) if args.speed else None
        try:
            feed = _open_feed(args, log, flt.active)
        except (SinkError, LogError) as exc:
            err(str(exc))
            return EXIT_BAD_INPUT
        try:
            if args.redecode:
                rows = _redecoded(log, args, fmt, feed)
            else:
                rows = ((*retimed(r.obj, r.text, r.time, fmt), r.time, r) for r in _stored(log))
            for obj, line, ts, made in rows:
                if not flt.matches(obj, line, ts):
                    continue
                if pacer is not None:
                    pacer.wait(ts)
                if feed is not None:
                    feed.serve(made)
                if args.quiet:
                    continue
                if args.json:
                    if obj is None:
                        continue
                    out.write(dumps_line(obj) + "\n")
                else:
                    out.write(line + "\n")
                if pacer is not None:
                    out.flush()
            if feed is not None:
                feed.finish()
        except LogError as exc:
            out.flush()
            bar.close()  # before the message: the bar shares stderr
            err(str(exc))
            report_skipped(log)
            return EXIT_BAD_INPUT
        finally:
            bar.close()
            if feed is not None:
                feed.close()
        out.flush()
        note_status(log)
        if report_skipped(log):
            return EXIT_BAD_INPUT
    return EXIT_OK


#: Records ``replay --browse`` keeps (the live monitor keeps the last 10,000).
BROWSE_KEEP = 200_000


def run_browse(args: argparse.Namespace) -> int:
    """``mbmon replay --browse``: the log in the interactive monitor, its raw bytes
    decoded again through the one flow (as ``--redecode``: the lines ``read`` prints),
    the command-line filters as the screen's first display filter."""
    from mbmon.commands.common import filter_text
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
        view = _replay_view(log, args, fmt)
        feed = MonitorFeed(
            view,
            title=f"mbmon replay {log.path.name}",
            keep=BROWSE_KEEP,
            annotator=annotator,
            profile=any("hrss" in spec for spec in opts.profile_specs),
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


def _stored(log: Any) -> Iterator[Any]:
    from mbmon.io.replay import logged_records

    return logged_records(log)


def _replay_view(log: Any, args: argparse.Namespace, fmt: Any = None) -> Any:
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


def _redecoded(
    log: Any, args: argparse.Namespace, fmt: Any, feed: ReplayFeed | None = None
) -> Iterator[tuple[dict[str, Any], str, float, Any]]:
    from mbmon.format import record_to_json
    from mbmon.hub import Hub
    from mbmon.io.replay import raw_items, recorded_annotator, recorded_options
    from mbmon.pipeline import Pipeline, PipelineConfig

    opts = recorded_options(log)
    view = _replay_view(log, args, fmt)
    annotator = recorded_annotator(log, opts)
    pipeline = Pipeline(annotator, PipelineConfig(timeout=opts.timeout, baudrate=opts.baud))
    with Hub(pipeline) as hub:  # the one loop every command runs, as `read` does
        if feed is not None:
            hub.add_listener(feed.chunks)
        for record in hub.iter_records(raw_items(log)):
            obj = record_to_json(record, view)
            yield obj, obj["line"], record.ts, record


def _open_feed(args: argparse.Namespace, log: Any, filtered: bool) -> ReplayFeed | None:
    """``--foxglove``: the live feed of what replay prints, else ``None``."""
    from mbmon.commands.common import open_foxglove
    from mbmon.io.mcap.layout import METADATA_NAME, TOPIC_STATE
    from mbmon.io.replay import recorded_options
    from mbmon.sinks.base import SinkContext

    if getattr(args, "foxglove", None) is None:
        return None
    opts = recorded_options(log)
    profiles = log.profiles()
    ctx = SinkContext(
        view=_replay_view(log, args),
        source=log.metadata.get(METADATA_NAME, {}).get("source", str(log.path)),
        profiles=profiles,
        profile_specs=opts.profile_specs if (profiles or TOPIC_STATE in log.topics) else [],
    )
    feed = open_foxglove(args, ctx)
    return ReplayFeed(feed, log, args.redecode, not filtered)
