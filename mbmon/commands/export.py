"""``mbmon export``: an MCAP log converted by the suffix of ``-o``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mbmon.commands.common import EXIT_BAD_INPUT, EXIT_OK, EXIT_USAGE
from mbmon.commands.logfile import (
    err,
    filter_failed,
    log_times,
    note_status,
    open_log,
    progress,
    report_skipped,
)
from mbmon.filters import add_filter_options
from mbmon.io.mcapcopy import copy_log
from mbmon.timefmt import add_time_option

EPILOG = """\
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


def register(sub: Any) -> None:
    """Add ``export`` to the CLI's sub-parsers."""
    fmt = argparse.RawDescriptionHelpFormatter

    export = sub.add_parser(
        "export",
        help="convert an MCAP log to .csv, .jsonl, .txt, .pcap, .pcapng (or a repaired .mcap)",
        description="Convert an MCAP log by the suffix of OUT: .csv (one row per frame), "
        ".jsonl (read --json lines), .txt (monitor lines), .pcap (Modbus/TCP re-wrapped in "
        "Ethernet/IPv4/TCP with consistent sequence numbers, original endpoints and times, "
        "the server port written as 502 so that Wireshark decodes it; RTU as link type 147), "
        ".mcap (every recovered message in a finished file).",
        epilog=EPILOG,
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


def run_export(args: argparse.Namespace) -> int:
    """``mbmon export``: the log converted by the suffix of ``-o``."""
    from mbmon.commands.common import check_outputs
    from mbmon.filters import FilterError
    from mbmon.io.mcap.reader import LogError
    from mbmon.sinks.base import SinkError

    target = Path(args.output)
    # the one check of read -w too: a known format, and never the input (device, inode)
    check_outputs([str(target)], [args.log])
    log, status = open_log(args.log, "export")
    if log is None:
        return status
    with log:
        try:
            fmt, flt = log_times(args, log)
        except FilterError as exc:
            return filter_failed(log, exc)
        refused = _refused(log, target.suffix.lower(), flt)
        if refused is not None:
            return refused
        bar = progress(log)
        try:
            written = _export(args, log, target, fmt, flt)
        except SinkError as exc:
            err(str(exc))
            return EXIT_BAD_INPUT
        except OSError as exc:
            err(f"{target}: cannot write: {exc.strerror or exc}")
            return EXIT_BAD_INPUT
        except LogError as exc:
            bar.close()  # before the message: the bar shares stderr
            err(f"{exc} (the output holds everything readable)")
            report_skipped(log)
            return EXIT_BAD_INPUT
        finally:
            bar.close()
        note_status(log)
        if report_skipped(log) or not written:
            return EXIT_BAD_INPUT
    return EXIT_OK


def _refused(log: Any, suffix: str, flt: Any) -> int | None:
    """The exit status when the export cannot be made (a usage error, or a log that
    gives nothing back: then no file is written), after saying why; else ``None``."""
    if suffix in _RAW_FORMATS and (
        flt.units is not None
        or flt.fcs is not None
        or flt.address is not None
        or flt.grep
        or flt.where is not None
    ):
        err(f"error: {suffix} export takes only --since/--until (it copies raw bytes)")
        return EXIT_USAGE
    if not log.finished and _recovers_nothing(log):
        # an output with no message in it would look like a repaired or converted
        # log and hide that nothing came back: say so and write no file
        err(f"{log.path}: nothing to export, no file written: {log.status.describe()}")
        return EXIT_BAD_INPUT
    return None


#: formats made of the log's raw bytes (the filters of records do not apply)
_RAW_FORMATS = (".pcap", ".pcapng", ".mcap")


def _export(args: argparse.Namespace, log: Any, target: Path, fmt: Any, flt: Any) -> bool:
    """Write ``target`` by its suffix; whether its writer took everything (a sink that
    failed on the way was reported by the hub and detached)."""
    from mbmon.filters import RecordFilter
    from mbmon.format import View
    from mbmon.io.replay import recorded_options
    from mbmon.sinks.base import SinkContext, open_sink

    suffix = target.suffix.lower()
    if suffix == ".mcap":
        copy_log(log, target, RecordFilter(since=flt.since, until=flt.until))
        return True
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
    if suffix in (".pcap", ".pcapng"):
        _export_pcap(
            log,
            target,
            ctx,
            flt,
            pcapng=suffix == ".pcapng",
            keep_segments=args.keep_segments,
            server_port=None if args.keep_port else args.server_port,
        )
        return True
    return write_records(log, open_sink(target, ctx), fmt, flt)


def write_records(log: Any, sink: Any, fmt: Any, flt: Any) -> bool:
    """The log's stored records, filtered, into ``sink`` through the hub, as ``read -w``
    hands a sink its records (the one listener contract): whether the sink took them
    all (a sink that raised was reported by the hub, closed and detached)."""
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.io.logsource import LogSource, StoredPipeline, run_stored
    from mbmon.sinks.select import Selection

    view = View(time_format=fmt)
    # records only: a sink's on_chunk/on_event are for a run's input, which a stored
    # record is not (the selection passes on the record hooks alone)
    with Hub(StoredPipeline(), [Selection([sink], view)]) as hub:
        run_stored(hub, LogSource(log, fmt, flt))
    return not hub.failures


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
        err(f"note: RTU and IP streams mixed: the other kind is in {sink.companion}")
