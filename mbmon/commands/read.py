"""``mbmon read``: a capture file or a raw RTU bus dump through the hub, to the console and logs."""

from __future__ import annotations

import argparse
import itertools
import os
import stat
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from mbmon.commands.common import (
    EXIT_BAD_INPUT,
    FrameBudget,
    UsageError,
    add_count_option,
    add_output_options,
    add_port_options,
    add_view_options,
    attach_outputs,
    check_outputs,
    check_rotation,
    err,
    exit_status,
    make_annotator,
    open_logs,
    open_trigger,
    positive,
    positive_int,
    profile_sources,
    view_and_filter,
)
from mbmon.commands.read_summary import detected_lines, report
from mbmon.filters import EXPRESSION_HELP, TIMES_HELP, add_filter_options
from mbmon.timefmt import add_time_option

EPILOG = """\
examples:
  mbmon read captures/hrss_ptp.pcap
      print every Modbus ADU as the robot's Modbus Monitor shows it
  mbmon read plant.pcapng --json > frames.jsonl
      one JSON object per line; Modbus/TCP on other ports is found by its structure
  mbmon read plant.pcapng --port 1502 --no-detect
      only ports 502 and 1502 are Modbus
  mbmon read cell.pcap --robot 192.168.0.10 --profile hrss
      label lines from the robot's point of view and add HRSS meaning
  mbmon read bus.pcap --rtu-port 4001          RTU frames carried in TCP/UDP port 4001
  mbmon read --rtu-raw bus.bin                 a raw byte dump of an RS485 bus
  cat /dev/ttyUSB0 | mbmon read --rtu-raw -    the same, as the bytes arrive
  mbmon read cell.pcap -c 20                   the first 20 frames only
  mbmon read cell.pcap --fc 6,16 --address 200-251 -t r
      only writes touching R200..R251, times relative to the first record
  mbmon read cell.pcap -w cell.mcap            also record an MCAP log (Foxglove)
  mbmon read week.pcap -w fault.mcap --trigger 'exception or timeout' --before 30s --after 10s
      keep only 40 s around each fault: one MCAP file per window

output lines: TIME  LABEL  [uUNIT tTID]  FUNCTION-CODE + DATA (hex)  | meaning
a summary goes to stderr at the end (-q: none)
exit status: 0 ok, 1 bad or damaged input (everything before the damage is printed) or
an output that failed, 2 usage, 130/143 stopped by Ctrl-C/SIGTERM (logs finished, summary)

"""

#: The first bytes of an MCAP file (mbmon's logs).
MCAP_MAGIC = b"\x89MCAP0\r\n"

#: ``detected_lines`` stays importable from here (``sniff`` says what port detection found)
__all__ = ["MCAP_MAGIC", "detected_lines", "register", "run"]


def register(sub: Any) -> None:
    """Add ``read`` to the CLI's sub-parsers."""
    read = sub.add_parser(
        "read",
        help="decode a capture file (pcap/pcapng) or a raw RTU bus dump",
        description="Decode every Modbus ADU in a capture file and print it as the robot's "
        "Modbus Monitor (manual Table 57) shows it, with its meaning.",
        epilog=EPILOG + textwrap.fill(TIMES_HELP, 80) + "\n\n" + textwrap.fill(EXPRESSION_HELP, 80),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    read.add_argument(
        "file", nargs="?", metavar="FILE", help="pcap or pcapng file (gzip too; - for stdin)"
    )
    src = read.add_argument_group("input")
    add_port_options(src)
    src.add_argument(
        "--rtu-raw",
        metavar="FILE",
        help="read FILE as a raw byte dump of an RS485 bus (RTU, both directions, no "
        "timing); a pipe, FIFO or serial device works too (- for stdin)",
    )
    src.add_argument(
        "--timeout",
        type=positive,
        default=1.0,
        metavar="S",
        help="report a request unanswered after S seconds of capture time (default 1.0)",
    )
    src.add_argument(
        "--baud",
        type=positive_int,
        metavar="N",
        help="RTU baud rate (silence gaps become health hints)",
    )
    src.add_argument(
        "--debug-core",
        action="store_true",
        help="say on stderr whether the compiled core or the Python pipeline read the "
        "input, and why (see docs/architecture.md)",
    )
    add_count_option(src)
    add_view_options(read)
    add_output_options(read)
    add_time_option(read)
    add_filter_options(read)
    read.set_defaults(func=run)


def _is_stream_input(path: str) -> bool:
    """A pipe, FIFO, socket or character device: read as it comes, print as it comes."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return stat.S_ISFIFO(mode) or stat.S_ISCHR(mode) or stat.S_ISSOCK(mode)


def _looks_like_mcap(path: str) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


def run(args: argparse.Namespace) -> int:
    """``mbmon read``: every record of the input to the logs, the console and the summary."""
    from mbmon.commands.common import Progress

    path = _input_path(args)
    check_outputs(args.write, [path])
    check_rotation(args)
    view, flt = view_and_filter(args)
    annotator = make_annotator(args.profile)
    if not os.path.exists(path):
        err(f"{path}: no such file")
        return EXIT_BAD_INPUT
    live = _is_stream_input(path)
    if not live and not args.rtu_raw and _looks_like_mcap(path):
        err(f"{path} is an MCAP log, not a capture: try 'mbmon replay {args.file}'")
        return EXIT_BAD_INPUT
    progress = Progress(f"reading {Path(path).name}")
    try:
        if not args.rtu_raw:
            from mbmon.commands.read_core import read_with_core

            done = read_with_core(
                path, args, view, flt, live=live, progress=progress, annotator=annotator
            )
            if done is not None:
                return done
        return _read_with_pipeline(args, path, view, flt, annotator, live, progress)
    finally:
        progress.close()


def _input_path(args: argparse.Namespace) -> str:
    """The one input of ``read`` (``FILE`` or ``--rtu-raw FILE``; ``-`` is stdin)."""
    if args.rtu_raw and args.file:
        raise UsageError("give either FILE or --rtu-raw FILE, not both")
    if not args.rtu_raw and not args.file:
        raise UsageError("read needs a FILE (pcap/pcapng) or --rtu-raw FILE")
    path: str = args.rtu_raw or args.file
    return "/dev/stdin" if path == "-" else path  # a pipe: the readers never seek


def _open_items(
    args: argparse.Namespace, path: str, progress: Any, stats: dict[str, Any]
) -> Iterator[Any]:
    """The input's chunks and events; :class:`~mbmon.sources.pcapfile.CaptureError`
    when it cannot be opened or its first record cannot be read (before any output
    is opened)."""
    if args.rtu_raw:
        from mbmon.sources.rawfile import read_rtu_raw

        return read_rtu_raw(path)
    from mbmon.sources.pcapfile import CaptureConfig, read_capture

    config = CaptureConfig(
        tcp_ports=frozenset({502, *args.port}),
        rtu_ports=frozenset(args.rtu_port),
        detect=not args.no_detect,
    )
    items = read_capture(path, config, progress=progress, stats=stats)
    first = next(items, None)  # a capture damaged at once fails here, before any output
    return items if first is None else itertools.chain((first,), items)


def _read_with_pipeline(
    args: argparse.Namespace,
    path: str,
    view: Any,
    flt: Any,
    annotator: Any,
    live: bool,
    progress: Any,
) -> int:
    """``read`` by the reference pipeline through the hub: logs, then the screen, then
    the summary; ``-c`` behind the filters. A signal at any instant ends it alike:
    the logs finished, the summary so far, 128 + the signal."""
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sinks.base import SinkError
    from mbmon.sinks.summary import Summary
    from mbmon.sources.pcapfile import CaptureError

    hub = Hub(Pipeline(annotator, PipelineConfig(timeout=args.timeout, baudrate=args.baud)))
    summary = None if args.quiet else Summary(view if args.robot else None)
    capture_stats: dict[str, Any] = {}
    gate = open_trigger(args)  # --trigger: the logs and the screen see only its windows
    logs: list[Any] = []
    interrupted = attached = False
    try:
        items = _open_items(args, path, progress, capture_stats)
        logs = open_logs(args.write, _context(args, path, view, annotator), args)
        attach_outputs(
            hub,
            logs=logs,
            screen=_screen(args, view, flt, live),
            summary=summary,
            budget=FrameBudget(args.count, hub.enough, flt, view) if args.count else None,
            gate=gate,
        )
        attached = True
        if live:  # a pipe may stall: the hub ticks meanwhile, so logs reach the disk
            from mbmon.sources.pipe import feed_pipe

            feed_pipe(hub, items)
        else:
            hub.run_items(items)
    except (CaptureError, SinkError) as exc:
        err(str(exc))
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        interrupted = True
    finally:
        hub.close()
        for sink in () if attached else logs:  # a signal came before the hub had them
            sink.close()
    if summary is not None:
        report(summary, capture_stats, args, timed=not args.rtu_raw)
    if interrupted:
        failed = {name for name, _why in hub.failures}
        for sink in logs:
            name = getattr(sink, "path", None)
            if name is not None and str(name) not in failed:
                err(f"interrupted; {name} was finished and is complete up to here")
    elif hub.errors:
        err(hub.errors[-1])
    return exit_status(hub, interrupted=interrupted)


def _context(args: argparse.Namespace, path: str, view: Any, annotator: Any) -> Any:
    """What the ``-w`` logs store besides the records (view, source, settings)."""
    from mbmon.sinks.base import SinkContext

    return SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=str(path),
        profiles=profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=args.timeout,
        baud=args.baud,
    )


def _screen(args: argparse.Namespace, view: Any, flt: Any, live: bool) -> Any:
    """The console behind the display filter (``None`` with ``-q``)."""
    if args.quiet:
        return None
    from mbmon.sinks.console import ConsoleListener

    console = ConsoleListener(sys.stdout, view, as_json=args.json, live=live)
    if flt is None or not flt.active:
        return console
    from mbmon.sinks.select import Selection

    return Selection([console], view, flt)
