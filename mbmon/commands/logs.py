"""The log commands ``mbmon replay``, ``mbmon info`` and ``mbmon export``: parsing and wiring.

:func:`add_subcommands` registers them on the CLI's subparsers; each ``run_*``
takes the parsed arguments and returns the exit status (0 ok, 1 unreadable or
damaged log — everything before the damage is still output —, 2 usage).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from mbmon.commands import replay_servers
from mbmon.commands.common import (
    EXIT_BAD_INPUT,
    EXIT_OK,
    EXIT_USAGE,
    UsageError,
    add_foxglove_option,
)
from mbmon.filters import add_filter_options
from mbmon.timefmt import add_time_option

_REPLAY_EPILOG = """\
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

_INFO_EPILOG = """\
examples:
  mbmon info cell.mcap          time span, messages per topic, streams, units, function
                                codes, exceptions, noise/CRC errors, robot commands
  mbmon info cell.mcap --json   the same as one JSON object
"""

_EXPORT_EPILOG = """\
examples:
  mbmon export cell.mcap -o frames.csv      one row per frame (spreadsheets)
  mbmon export cell.mcap -o frames.jsonl    the read --json lines
  mbmon export cell.mcap -o monitor.txt     the monitor lines
  mbmon export cell.mcap -o cell.pcap       Ethernet/IP/TCP packets Wireshark decodes with
                                            no option: one ADU per segment, server port 502
                                            (RTU buses: link type 147, one frame per record;
                                            a note prints the tshark option)
  mbmon export cell.mcap -o cell.pcap --keep-port
                                            the original ports; a note prints the option
                                            (tshark -d tcp.port==1502,mbtcp)
  mbmon export cell.mcap -o cell.pcapng     the same as pcapng, the changes marked as comments
  mbmon export cell.mcap -o cell.parquet    one row per record: DuckDB, Spark, Trino (docs/fleet.md)
  mbmon export crashed.mcap -o fixed.mcap   rewrite an unfinished log as a finished one

Filters (--unit, --fc, --address, --grep) apply to .csv, .jsonl and .txt; --since and
--until to every format.
"""


def add_subcommands(sub: Any) -> None:
    """Register ``replay``, ``info`` and ``export`` on the CLI's subparsers."""
    fmt = argparse.RawDescriptionHelpFormatter

    replay = sub.add_parser(
        "replay",
        help="print a recorded MCAP log as the monitor showed it live (with filters)",
        description="Print the monitor lines of an MCAP log written with -w FILE.mcap, "
        "exactly as they were shown live, or the read --json objects; optionally "
        "filtered, re-decoded from the raw bytes, or paced like the original.",
        epilog=_REPLAY_EPILOG + "\n" + replay_servers.EPILOG,
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

    info = sub.add_parser(
        "info",
        help="summarise an MCAP log: span, topics, streams, function codes, errors, commands",
        description="Summarise an MCAP log written by mbmon. An unfinished log (the "
        "recording was killed) is read as far as it goes; info says how much was recovered.",
        epilog=_INFO_EPILOG,
        formatter_class=fmt,
    )
    info.add_argument("log", metavar="LOG.mcap", help="an MCAP log written by mbmon")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    add_time_option(info, since_until=False)
    info.set_defaults(func=run_info)

    export = sub.add_parser(
        "export",
        help="convert an MCAP log to .csv, .jsonl, .txt, .pcap, .pcapng (or a repaired .mcap)",
        description="Convert an MCAP log by the suffix of OUT: .csv (one row per frame), "
        ".jsonl (read --json lines), .txt (monitor lines), .pcap (Modbus/TCP re-wrapped in "
        "Ethernet/IPv4/TCP with consistent sequence numbers, original endpoints and times, "
        "the server port written as 502 so that Wireshark decodes it; RTU as link type 147), "
        ".mcap (every recovered message in a finished file).",
        epilog=_EXPORT_EPILOG,
        formatter_class=fmt,
    )
    export.add_argument("log", metavar="LOG.mcap", help="an MCAP log written by mbmon")
    export.add_argument("-o", "--output", required=True, metavar="OUT", help="output file")
    export.add_argument(
        "--keep-segments",
        action="store_true",
        help=".pcap: keep the original TCP segmentation (default: one ADU per segment, so "
        "that Wireshark dissects every ADU)",
    )
    ports = export.add_mutually_exclusive_group()
    ports.add_argument(
        "--server-port",
        type=_port,
        default=502,
        metavar="N",
        help=".pcap: write the server port of every Modbus/TCP and Modbus/UDP stream as N "
        "(default 502, which Wireshark decodes as Modbus with no option; a note names "
        "each original port)",
    )
    ports.add_argument(
        "--keep-port",
        action="store_true",
        help=".pcap: write the original server ports; a note gives the tshark option "
        "(-d tcp.port==N,mbtcp) for a port other than 502",
    )
    add_time_option(export)
    add_filter_options(export)
    export.set_defaults(func=run_export)


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 1..65535: {text}")
    return value


def _speed(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text}")
    return value


# --------------------------------------------------------------------------- shared


def _err(message: str) -> None:
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


def _open(path: str, command: str) -> tuple[Any, int]:
    """The log at ``path`` and 0, or ``None`` and the exit status after saying, in one
    line, why it cannot be read (a packet capture: exit 2 and ``mbmon read`` suggested)."""
    from mbmon.io.mcap.reader import LogError, McapLog

    try:
        return McapLog(path), EXIT_OK
    except LogError as exc:
        if is_capture(path):
            _err(f"error: {path} is a packet capture, not an MCAP log: "
                 f"use 'mbmon read {path}' (add -w LOG.mcap to record one)")  # fmt: skip
            return None, EXIT_USAGE
        text = str(exc)
        if "not an MCAP file" in text:
            text += f"; {command} reads the MCAP logs written by 'mbmon read ... -w LOG.mcap'"
        _err(text)
        return None, EXIT_BAD_INPUT


def _progress(log: Any) -> Any:
    """A progress bar on stderr for a big log, when stderr is a terminal (never stdout's):
    the one ``read`` shows for big captures, fed by the reader after every chunk."""
    from mbmon.commands.common import Progress

    bar = Progress(f"reading {log.path.name}")
    log.progress = bar
    return bar


def _log_times(args: argparse.Namespace, log: Any) -> tuple[Any, Any]:
    """The log's time format (``-t``, origin and date rule from its span) and filter."""
    from mbmon.filters import build_filter
    from mbmon.io.replay import first_record_time
    from mbmon.timefmt import TimeFormat

    start = first_record_time(log)
    # the rule `read` prints by while streaming (a date on times of another day than
    # the first record's), so replayed lines are the lines read printed
    fmt = TimeFormat(getattr(args, "time_format", "a"), origin=start)
    return fmt, build_filter(args, start, fmt)


def _filter_failed(log: Any, exc: Exception) -> int:
    """A filter that cannot be built: a usage error (2), unless no record of the log can
    be read because of damage (``--since +5s`` has no start): then the damage (1)."""
    status = log.status
    if status.stopped_at is not None and "no records" in str(exc):
        _err(f"{log.path}: no record can be read: {status.problem} (at byte {status.stopped_at})")
        return EXIT_BAD_INPUT
    _err(f"error: {exc}")
    return EXIT_USAGE


def _retimed(
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


def _note_status(log: Any) -> None:
    status = log.status
    if not status.finished:
        _err(f"note: {log.path}: {status.describe()}")


def _report_skipped(log: Any) -> bool:
    """Say which damaged messages the reading left out (stderr); whether there were any."""
    lines = log.status.skipped_lines()
    if lines:
        _err(f"{log.path}: {lines[0]}")
        for line in lines[1:]:
            print(line, file=sys.stderr)
    return bool(lines)


# --------------------------------------------------------------------------- replay


def run_replay(args: argparse.Namespace) -> int:
    """``mbmon replay``: stored lines (or --json objects, or a re-decode), filtered and paced."""
    from mbmon.filters import FilterError, Pacer
    from mbmon.io.mcap.reader import LogError
    from mbmon.sinks.base import SinkError
    from mbmon.sinks.jsonl import dumps_line

    if replay_servers.wanted(args):  # against servers: emulate (--serve) or re-send (--to)
        if args.quiet:
            _err("error: -q silences the printed log; --serve and --to print only their report")
            return EXIT_USAGE
        return replay_servers.run(args, _open, _log_times)
    try:
        replay_servers.check_without_mode(args)
    except UsageError as exc:
        _err(f"error: {exc}")
        return EXIT_USAGE
    if getattr(args, "browse", False):
        return run_browse(args)
    if (args.robot or args.robot_client) and not args.redecode:
        _err("error: --robot relabels lines only with --redecode (stored lines are as recorded)")
        return EXIT_USAGE
    log, status = _open(args.log, "replay")
    if log is None:
        return status
    out = sys.stdout
    bar = _progress(log)
    with log:
        try:
            fmt, flt = _log_times(args, log)
        except FilterError as exc:
            return _filter_failed(log, exc)
        pacer = Pacer(args.speed) if args.speed else None
        try:
            feed = _ReplayFeed.open(args, log, flt.active)
        except (SinkError, LogError) as exc:
            _err(str(exc))
            return EXIT_BAD_INPUT
        try:
            if args.redecode:
                rows = _redecoded(log, args, fmt, feed)
            else:
                rows = ((*_retimed(r.obj, r.text, r.time, fmt), r.time, r) for r in _stored(log))
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
            _err(str(exc))
            _report_skipped(log)
            return EXIT_BAD_INPUT
        finally:
            bar.close()
            if feed is not None:
                feed.close()
        out.flush()
        _note_status(log)
        if _report_skipped(log):
            return EXIT_BAD_INPUT
    return EXIT_OK


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
        _err("error: --browse shows the log on the screen: no --json, --speed or --foxglove")
        return EXIT_USAGE
    if not (sys.stdout.isatty() and sys.stdin.isatty()):
        _err("error: --browse needs a terminal (stdin and stdout); without one, replay prints")
        return EXIT_USAGE
    log, status = _open(args.log, "replay")
    if log is None:
        return status
    with log:
        if TOPIC_RAW not in log.topics:
            _err(f"error: {args.log} has no {TOPIC_RAW} (raw bytes) to browse; "
                 "mbmon replay prints its stored lines")  # fmt: skip
            return EXIT_BAD_INPUT
        try:
            fmt, _flt = _log_times(args, log)
            opts = recorded_options(log)
            annotator = recorded_annotator(log, opts)
        except (FilterError, LogError) as exc:
            _err(f"error: {exc}")
            return EXIT_USAGE if isinstance(exc, FilterError) else EXIT_BAD_INPUT
        view = _replay_view(log, args, fmt)
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
            _err(message)
        _note_status(log)
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
    log: Any, args: argparse.Namespace, fmt: Any, feed: _ReplayFeed | None = None
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


class _ReplayFeed:
    """``replay --foxglove``: what replay prints, served live (paced by ``--speed``).

    Stored lines: the log's own messages of each printed record, on every topic
    (and, unfiltered, its raw chunks and the writer's stats), read alongside in
    file order from a second reader of the log. ``--redecode``: the records as
    a log of the re-decode would hold them (:class:`~mbmon.sinks.foxglove.FoxgloveFeed`).
    """

    def __init__(self, feed: Any, log: Any, redecode: bool, everything: bool) -> None:
        self.feed = feed
        self.everything = everything
        self._log: Any = None
        self._messages: Iterator[Any] | None = None
        self._held: tuple[int | None, Any] | None = None
        if not redecode:
            from mbmon.io.mcap.reader import McapLog

            try:
                self._log = McapLog(log.path)
            except Exception:
                feed.close()
                raise
            self._messages = self._log.messages(feed.topics)

    @classmethod
    def open(cls, args: argparse.Namespace, log: Any, filtered: bool) -> _ReplayFeed | None:
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
        return cls(feed, log, args.redecode, not filtered)

    @property
    def chunks(self) -> Any:
        """A hub listener that serves raw chunks (unfiltered re-decodes only)."""
        feed, everything = self.feed, self.everything

        class _Chunks:
            name = "foxglove"

            def on_chunk(self, chunk: Any) -> None:
                if everything:
                    feed.on_chunk(chunk)

        return _Chunks()

    def serve(self, made: Any) -> None:
        """Serve one printed row: a re-decoded record, or a stored record's messages."""
        if self._messages is None:
            self.feed.on_records([made])
            return
        self._serve_upto(made.index)

    def finish(self) -> None:
        """Unfiltered: what the log holds after the last record (raw chunks, stats)."""
        if self._messages is not None and self.everything:
            self._serve_upto(None)

    def _serve_upto(self, index: int | None) -> None:
        """Serve the stored messages of record ``index`` (skip those of earlier records)."""
        assert self._messages is not None
        while True:
            if self._held is None:
                msg = next(self._messages, None)
                if msg is None:
                    return
                self._held = (_record_index(msg), msg)
            of, msg = self._held
            if index is not None and of is not None and of > index:
                return
            self._held = None
            if of == index if of is not None else self.everything:
                self.feed.publish(msg.topic, msg.log_time, msg.raw)

    def close(self) -> None:
        try:
            self.feed.close()
        finally:
            if self._log is not None:
                self._log.close()


def _record_index(msg: Any) -> int | None:
    """Which record a stored message belongs to (``None``: raw chunks, the writer's stats)."""
    from mbmon.io.mcap.layout import TOPIC_MONITOR
    from mbmon.io.mcap.reader import LogError

    try:
        data = msg.json()
    except LogError:
        return None
    if not isinstance(data, dict):
        return None
    index = data.get("line") if msg.topic == TOPIC_MONITOR else data.get("index")
    return index if isinstance(index, int) and not isinstance(index, bool) else None


# --------------------------------------------------------------------------- info


def summarize(log: Any) -> dict[str, Any]:
    """Everything ``mbmon info`` reports, as one JSON-able dict (one pass over the log)."""
    from mbmon.io.mcap.layout import (
        METADATA_NAME,
        TOPIC_COMMANDS,
        TOPIC_EVENTS,
        TOPIC_FRAMES,
        TOPIC_RAW,
    )
    from mbmon.io.replay import FRAME_KINDS, payload, recorded_options, stored_profile_names

    topics: Counter[str] = Counter({t: 0 for t in log.topics})
    first = last = None
    streams: dict[int, dict[str, Any]] = {}
    units: Counter[int] = Counter()
    fcs: dict[int, Counter[str]] = {}
    exceptions: Counter[tuple[int, int]] = Counter()
    noise_runs = noise_bytes = crc_errors = malformed = unsolicited = 0
    noise_reasons: Counter[str] = Counter()
    events: Counter[str] = Counter()
    phases: Counter[str] = Counter()
    outcomes: list[dict[str, Any]] = []
    latencies: list[float] = []
    writer_stats: dict[str, Any] | None = None
    error: str | None = None
    from mbmon.io.mcap.reader import LogError

    try:
        for msg in log.messages():
            topics[msg.topic] += 1
            t = msg.log_time
            first = t if first is None or t < first else first
            last = t if last is None or t > last else last
            if msg.topic not in (TOPIC_RAW, TOPIC_FRAMES, TOPIC_EVENTS, TOPIC_COMMANDS):
                continue
            obj = payload(log, msg)  # the fields of a damaged message are not counted
            if obj is None:
                continue
            if msg.topic == TOPIC_RAW:
                sid = obj.get("stream")
                if sid is not None and sid not in streams:
                    streams[sid] = {
                        "id": sid,
                        "transport": obj.get("transport"),
                        "client": obj.get("client"),
                        "server": obj.get("server"),
                        "chunks": 0,
                        "bytes": 0,
                        "frames": 0,
                    }
                if obj.get("type") == "chunk" and sid is not None:
                    b64 = str(obj.get("data") or "")
                    streams[sid]["chunks"] += 1
                    streams[sid]["bytes"] += len(b64) * 3 // 4 - b64.count("=", -2)
                continue
            kind = obj.get("kind")
            if msg.topic == TOPIC_FRAMES and kind in FRAME_KINDS:
                fc = obj.get("fc")
                sid = obj.get("stream")
                if sid is not None:
                    streams.setdefault(
                        sid,
                        {"id": sid, "transport": obj.get("transport"), "client": None,
                         "server": None, "chunks": 0, "bytes": 0, "frames": 0},
                    )["frames"] += 1  # fmt: skip
                if obj.get("unit") is not None:
                    units[obj["unit"]] += 1
                if isinstance(fc, int):
                    fcs.setdefault(fc, Counter())[kind] += 1
                if kind == "exception" and isinstance(fc, int):
                    exceptions[(fc, obj.get("exception_code") or 0)] += 1
                if obj.get("crc_ok") is False:
                    crc_errors += 1
                if obj.get("malformed"):
                    malformed += 1
                if kind != "request" and obj.get("request_index") is None:
                    unsolicited += 1
                if obj.get("latency_ms") is not None:
                    latencies.append(float(obj["latency_ms"]))
            elif msg.topic == TOPIC_FRAMES and kind == "noise":
                noise_runs += 1
                pdu = obj.get("pdu") or ""
                noise_bytes += (len(pdu) + 1) // 3
                reason = str(obj.get("malformed") or "")
                noise_reasons[reason] += 1
                if "crc" in reason.lower():
                    crc_errors += 1
            elif msg.topic == TOPIC_EVENTS and kind == "event":
                if obj.get("index") is None:
                    writer_stats = obj.get("info")
                else:
                    events[str(obj.get("event"))] += 1
            elif msg.topic == TOPIC_COMMANDS:
                cmd = obj.get("command") or {}
                phase = str(cmd.get("phase"))
                phases[phase] += 1
                if phase in ("success", "fail"):
                    outcomes.append(
                        {
                            "time": obj.get("time"),
                            "unit": obj.get("unit"),
                            "phase": phase,
                            "text": cmd.get("text"),
                            "duration": cmd.get("duration"),
                        }
                    )
    except LogError as exc:
        error = str(exc)
    meta = log.metadata.get(METADATA_NAME, {})
    command_line = recorded_options(log).command_line
    status = log.status
    from mbmon.format import exception_name, function_name

    return {
        "file": str(log.path),
        "size": log.size,
        "finished": status.finished,
        "recovered_messages": status.messages,
        "stopped_at": status.stopped_at,
        "problem": status.problem,
        "error": error,
        "damaged_messages": list(status.skipped.values()),
        "status": status.describe(),
        "recorded_by": meta.get("version"),
        "command_line": command_line,
        "source": meta.get("source"),
        "profiles": stored_profile_names(log),
        "profile_attachments": [name for name, _ in log.profiles()],
        "robot": meta.get("robot") or None,
        "start": first / 1e9 if first is not None else None,
        "end": last / 1e9 if last is not None else None,
        "duration": (last - first) / 1e9 if first is not None and last is not None else None,
        "topics": dict(sorted(topics.items())),
        "streams": [streams[k] for k in sorted(streams)],
        "units": {str(k): v for k, v in sorted(units.items())},
        "function_codes": {
            f"{fc}": {"name": function_name(fc), **dict(c), "total": sum(c.values())}
            for fc, c in sorted(fcs.items())
        },
        "exceptions": [
            {"fc": fc, "code": code, "name": exception_name(code), "count": n}
            for (fc, code), n in sorted(exceptions.items())
        ],
        "noise": {"runs": noise_runs, "bytes": noise_bytes, "reasons": dict(noise_reasons)},
        "crc_errors": crc_errors,
        "malformed": malformed,
        "unsolicited": unsolicited,
        "latency_ms": (
            {
                "min": min(latencies),
                "avg": round(sum(latencies) / len(latencies), 3),
                "max": max(latencies),
            }
            if latencies
            else None
        ),
        "events": dict(sorted(events.items())),
        "commands": {"phases": dict(phases), "outcomes": outcomes},
        "writer_stats": writer_stats,
    }


def _print_info(s: dict[str, Any], out: IO[str], mode: str = "a") -> None:
    """The summary as text; times in the ``-t`` mode ``mode`` (the span with its date)."""
    from mbmon.timefmt import TimeFormat, human_span

    fmt = TimeFormat.for_span(mode, s["start"], s["end"])
    dated = TimeFormat({"a": "ad", "u": "ud"}.get(mode, mode), origin=s["start"])

    def _when(ts: float | None, fmt: TimeFormat = fmt) -> str:
        return "-" if ts is None else fmt.text(ts)

    w = out.write
    w(f"file:        {s['file']} ({s['size']} bytes)\n")
    w(f"state:       {s['status']}\n")
    if s["error"]:
        w(f"damage:      {s['error']}\n")
    if s["damaged_messages"]:
        w(f"damaged:     {len(s['damaged_messages'])} messages left out (see stderr)\n")
    if s["recorded_by"]:
        w(f"recorded by: mbmon {s['recorded_by']}: {' '.join(s['command_line'])}\n")
    if s["source"]:
        w(f"source:      {s['source']}\n")
    w(f"profiles:    {', '.join(s['profiles']) or '-'}")
    if s["profile_attachments"]:
        w(f" (attached: {', '.join(s['profile_attachments'])})")
    w("\n")
    if s["robot"]:
        w(f"robot:       {s['robot']}\n")
    dur = f" ({human_span(s['duration'])})" if s["duration"] is not None else ""
    w(f"time span:   {_when(s['start'], dated)} .. {_when(s['end'], dated)}{dur}\n")
    w("messages per topic:\n")
    for topic, n in s["topics"].items():
        w(f"  {topic:<18} {n}\n")
    w(f"streams: {len(s['streams'])}\n")
    for st in s["streams"][:50]:
        peers = (
            st["client"] if st["client"] == st["server"] else f"{st['client']} <> {st['server']}"
        )
        w(
            f"  #{st['id']} {st['transport']} {peers}: {st['frames']} frames, "
            f"{st['chunks']} chunks, {st['bytes']} bytes\n"
        )
    if len(s["streams"]) > 50:
        w(f"  ... {len(s['streams']) - 50} more\n")
    units = ", ".join(f"{u} ({n} frames)" for u, n in s["units"].items())
    w(f"units:       {units or '-'}\n")
    w("function codes:\n" if s["function_codes"] else "function codes: -\n")
    for fc, c in s["function_codes"].items():
        parts = [f"{k}s {c[k]}" for k in ("request", "response", "exception") if c.get(k)]
        w(f"  {int(fc):02X} {c['name']}: {c['total']} ({', '.join(parts)})\n")
    if s["exceptions"]:
        w("exceptions:\n")
        for e in s["exceptions"]:
            w(f"  fc {e['fc']:02X}: {e['code']:02X} {e['name']}: {e['count']}\n")
    else:
        w("exceptions:  none\n")
    nz = s["noise"]
    reasons = "; ".join(f"{r or '?'}: {n}" for r, n in nz["reasons"].items())
    reasons = f" ({reasons})" if reasons else ""
    w(f"noise:       {nz['runs']} runs, {nz['bytes']} bytes{reasons}\n")
    w(f"CRC errors:  {s['crc_errors']}\n")
    w(f"malformed:   {s['malformed']}   unsolicited responses: {s['unsolicited']}\n")
    if s["latency_ms"]:
        lat = s["latency_ms"]
        w(f"latency:     min {lat['min']} ms, avg {lat['avg']} ms, max {lat['max']} ms\n")
    ev = ", ".join(f"{k} {v}" for k, v in s["events"].items())
    w(f"events:      {ev or 'none'}\n")
    cmds = s["commands"]
    if cmds["phases"]:
        ph = ", ".join(f"{k} {v}" for k, v in cmds["phases"].items())
        w(f"commands:    {ph}\n")
        for o in cmds["outcomes"][:30]:
            dur = f" after {o['duration']:.3f} s" if o["duration"] is not None else ""
            w(f"  {_when(o['time'])} unit {o['unit']}: {o['phase']}{dur}: {o['text']}\n")
        if len(cmds["outcomes"]) > 30:
            w(f"  ... {len(cmds['outcomes']) - 30} more outcomes\n")
    else:
        w("commands:    none\n")


def run_info(args: argparse.Namespace) -> int:
    """``mbmon info``: the summary of a log (text or --json)."""

    log, status = _open(args.log, "info")
    if log is None:
        return status
    bar = _progress(log)
    with log:
        try:
            summary = summarize(log)
        finally:
            bar.close()
    if args.json:
        from mbmon.format import finite

        print(json.dumps(finite(summary), ensure_ascii=False, indent=2, default=str))
    else:
        _print_info(summary, sys.stdout, args.time_format)
    if summary["error"]:
        _err(summary["error"])
    _report_skipped(log)
    return EXIT_BAD_INPUT if summary["error"] or summary["damaged_messages"] else EXIT_OK


# --------------------------------------------------------------------------- export


def run_export(args: argparse.Namespace) -> int:
    """``mbmon export``: the log converted by the suffix of ``-o``."""
    from mbmon.commands.common import check_outputs
    from mbmon.filters import FilterError, RecordFilter
    from mbmon.format import View
    from mbmon.io.mcap.reader import LogError
    from mbmon.io.replay import recorded_options
    from mbmon.sinks.base import SinkContext, SinkError, open_sink

    target = Path(args.output)
    suffix = target.suffix.lower()
    # the one check of read -w too: a known format, and never the input (device, inode)
    check_outputs([str(target)], [args.log])
    log, status = _open(args.log, "export")
    if log is None:
        return status
    with log:
        try:
            fmt, flt = _log_times(args, log)
        except FilterError as exc:
            return _filter_failed(log, exc)
        if suffix in (".pcap", ".pcapng", ".mcap") and (
            flt.units is not None
            or flt.fcs is not None
            or flt.address is not None
            or flt.grep
            or flt.where is not None
        ):
            _err(f"error: {suffix} export takes only --since/--until (it copies raw bytes)")
            return EXIT_USAGE
        if not log.finished and _recovers_nothing(log):
            # an output with no message in it would look like a repaired or converted
            # log and hide that nothing came back: say so and write no file
            _err(f"{log.path}: nothing to export, no file written: {log.status.describe()}")
            return EXIT_BAD_INPUT
        opts = recorded_options(log)
        ctx = SinkContext(
            view=View(robot=opts.robot, robot_is_client=opts.robot_is_client, time_format=fmt),
            command_line=opts.command_line,
            source=str(log.path),
            profiles=log.profiles(),
            profile_specs=opts.profile_specs,
            timeout=opts.timeout,
            baud=opts.baud,
        )
        bar = _progress(log)
        try:
            if suffix == ".mcap":
                _export_mcap(log, target, RecordFilter(since=flt.since, until=flt.until))
            elif suffix in (".pcap", ".pcapng"):
                _export_pcap(
                    log,
                    target,
                    ctx,
                    flt,
                    pcapng=suffix == ".pcapng",
                    keep_segments=args.keep_segments,
                    server_port=None if args.keep_port else args.server_port,
                )
            else:
                from mbmon.io.replay import logged_records

                with open_sink(target, ctx) as sink:
                    assert hasattr(sink, "write_logged")  # .txt .jsonl .csv .parquet
                    for rec in logged_records(log):
                        obj, line = _retimed(rec.obj, rec.text, rec.time, fmt)
                        if flt.matches(obj, line, rec.time):
                            sink.write_logged(obj, line)
        except SinkError as exc:
            _err(str(exc))
            return EXIT_BAD_INPUT
        except OSError as exc:
            _err(f"{target}: cannot write: {exc.strerror or exc}")
            return EXIT_BAD_INPUT
        except LogError as exc:
            bar.close()  # before the message: the bar shares stderr
            _err(f"{exc} (the output holds everything readable)")
            _report_skipped(log)
            return EXIT_BAD_INPUT
        finally:
            bar.close()
        _note_status(log)
        if _report_skipped(log):
            return EXIT_BAD_INPUT
    return EXIT_OK


def _recovers_nothing(log: Any) -> bool:
    """Whether an unfinished log gives back no message at all (its first chunk is
    missing or damaged); reads at most that chunk."""
    from mbmon.io.mcap.reader import LogError

    try:
        return next(iter(log.messages()), None) is None
    except LogError:
        return True


def _export_pcap(
    log: Any,
    target: Path,
    ctx: Any,
    flt: Any,
    *,
    keep_segments: bool,
    server_port: int | None,
    pcapng: bool = False,
) -> None:
    """The raw bytes as a pcap (or ``pcapng``): one ADU per TCP segment unless
    ``keep_segments``; Modbus server ports written as ``server_port`` unless it is
    ``None`` (the sink's notes, on stderr, name the original ports, or the tshark
    option a kept port needs; pcapng also carries them as comments)."""
    from mbmon.hub import hooks_of
    from mbmon.io.replay import raw_items
    from mbmon.sinks.pcap import PcapngSink, PcapSink

    cls = PcapngSink if pcapng else PcapSink
    with cls(target, ctx, adu_segments=not keep_segments, server_port=server_port) as sink:
        take = hooks_of(sink).item
        for item in raw_items(log):
            if flt.since is not None and item.ts < flt.since:
                continue
            if flt.until is not None and item.ts > flt.until:
                continue
            take(item)
    if sink.companion is not None:
        _err(f"note: RTU and IP streams mixed: the other kind is in {sink.companion}")


def _export_mcap(log: Any, target: Path, flt: Any) -> None:
    """Copy every (recovered) message into a new, finished and indexed MCAP file."""
    from mbmon import __version__
    from mbmon.io.mcap.layout import TOPIC_SCHEMAS, schema_text
    from mbmon.io.mcap.writer import McapFileWriter

    with open(target, "wb") as f:
        writer = McapFileWriter(f)
        writer.start(library=f"mbmon {__version__}")
        channels: dict[str, int] = {}
        for name, data in log.metadata.items():
            writer.add_metadata(name, data)
        for att in log.attachments:
            writer.add_attachment(0, att.log_time, att.name, att.media_type, att.data)

        def channel(topic: str) -> int:
            cid = channels.get(topic)
            if cid is None:
                stored = log.schema_of(topic)
                if stored is not None:
                    name, encoding, data = stored
                else:
                    name = TOPIC_SCHEMAS.get(topic, "")
                    encoding, data = ("jsonschema", schema_text(name)) if name else ("", b"")
                sid = writer.register_schema(name, encoding, data) if name else 0
                cid = writer.register_channel(topic, "json", sid)
                channels[topic] = cid
            return cid

        for topic in TOPIC_SCHEMAS:
            channel(topic)
        try:
            for msg in log.messages():
                ts = msg.log_time / 1e9
                if flt.since is not None and ts < flt.since:
                    continue
                if flt.until is not None and ts > flt.until:
                    continue
                writer.add_message(channel(msg.topic), msg.log_time, msg.raw)
        finally:
            writer.finish()
