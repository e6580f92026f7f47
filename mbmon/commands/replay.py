"""``mbmon replay``: a recorded MCAP log printed as the monitor showed it live (or its
``--json`` objects, or a re-decode), filtered and paced; ``--browse`` in the monitor;
``--serve``/``--to`` against servers (:mod:`mbmon.commands.replay_servers`).
"""

from __future__ import annotations

import argparse
import sys
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
    replay_view,
    report_skipped,
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
    """``mbmon replay``: the log's stored lines (or --json objects, or a re-decode),
    filtered and paced by its source, printed by the console listener ``read`` uses."""
    from mbmon.filters import FilterError
    from mbmon.io.mcap.reader import LogError
    from mbmon.sinks.base import SinkError

    status = _other_mode(args)
    if status is not None:
        return status
    log, status = open_log(args.log, "replay")
    if log is None:
        return status
    bar = progress(log)
    with log:
        try:
            fmt, flt = log_times(args, log)
        except FilterError as exc:
            return filter_failed(log, exc)
        try:
            feed = _open_feed(args, log, flt.active)
        except (SinkError, LogError) as exc:
            err(str(exc))
            return EXIT_BAD_INPUT
        try:
            _replay(args, log, fmt, flt, feed)
        except LogError as exc:
            bar.close()  # before the message: the bar shares stderr
            err(str(exc))
            report_skipped(log)
            return EXIT_BAD_INPUT
        finally:
            bar.close()
        note_status(log)
        if report_skipped(log):
            return EXIT_BAD_INPUT
    return EXIT_OK


def _other_mode(args: argparse.Namespace) -> int | None:
    """Run ``--serve``/``--to`` or ``--browse`` and give their status, or say what is
    wrong with the options (2); ``None`` when replay prints the log."""
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
        from mbmon.commands.browse import run_browse

        return run_browse(args)
    if (args.robot or args.robot_client) and not args.redecode:
        err("error: --robot relabels lines only with --redecode (stored lines are as recorded)")
        return EXIT_USAGE
    return None


def _replay(
    args: argparse.Namespace, log: Any, fmt: Any, flt: Any, feed: ReplayFeed | None
) -> None:
    """One run: the log as a paced source into the hub, the console (and ``feed``) out.

    Stored records are filtered by the source and pass the hub as they are; a
    re-decode's raw items go through the pipeline and its records are filtered
    in front of the screen, as ``read`` filters them. The console (and the live
    feed) sees only what passes; the feed is closed with the hub, also on damage.
    """
    from mbmon.filters import Pacer
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.io.logsource import LogSource, StoredPipeline, run_stored
    from mbmon.sinks.console import ConsoleListener
    from mbmon.sinks.select import Selection

    pacer = Pacer(args.speed) if args.speed else None
    source = LogSource(log, fmt, flt, pacer=pacer, raw=args.redecode, need_json=args.json)
    view = replay_view(log, args, fmt) if args.redecode else View(time_format=fmt)
    shown: list[Any] = [] if feed is None else [feed]
    if not args.quiet:  # paced: every line out as it is due
        shown.append(ConsoleListener(sys.stdout, view, as_json=args.json, live=pacer is not None))
    # each behind its own selection: a closed stdout (| head) does not stop the feed
    selected = flt if args.redecode else None  # stored records: the source filtered them
    listeners = [Selection([listener], view, selected) for listener in shown]
    if not args.redecode:
        with Hub(StoredPipeline(), listeners) as hub:
            run_stored(hub, source)
            if feed is not None:
                feed.finish()
        return
    from mbmon.io.replay import recorded_annotator, recorded_options
    from mbmon.pipeline import Pipeline, PipelineConfig

    # the hub first, so that it closes the feed and the console whatever happens next
    # (the recorded profiles may not load: a damaged log)
    with Hub(listeners=[] if feed is None else [feed.chunks]) as hub:
        for listener in listeners:
            hub.add_listener(listener)
        opts = recorded_options(log)
        hub.pipeline = Pipeline(
            recorded_annotator(log, opts), PipelineConfig(timeout=opts.timeout, baudrate=opts.baud)
        )
        hub.run_items(source.items())
        if feed is not None:
            feed.finish()


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
        view=replay_view(log, args),
        source=log.metadata.get(METADATA_NAME, {}).get("source", str(log.path)),
        profiles=profiles,
        profile_specs=opts.profile_specs if (profiles or TOPIC_STATE in log.topics) else [],
    )
    feed = open_foxglove(args, ctx)
    return ReplayFeed(feed, log, args.redecode, not filtered)
