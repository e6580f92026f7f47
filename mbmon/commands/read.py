"""``mbmon read``: a capture file or a raw RTU bus dump through the hub, to the console and logs."""

from __future__ import annotations

import argparse
import os
import sys
import textwrap
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
    view_and_filter,
)
from mbmon.commands.read_core import core_hand_off, log_context
from mbmon.commands.read_summary import capture_stats, detected_lines, report
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
  mbmon read mon.pcap tue.pcap -w week.mcap    several captures, one after another
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
        "file",
        nargs="*",
        metavar="FILE",
        help="pcap or pcapng file (gzip too; - for stdin); several are read one after "
        "another, each decoded as it is alone, into one output",
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


def _looks_like_mcap(path: str) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


def run(args: argparse.Namespace) -> int:
    """``mbmon read``: options → the inputs' sources (:mod:`mbmon.sources.files`) and
    the listeners (logs, the console, the summary) → ``run_sources`` → one exit status.
    The compiled core may take the whole input first (its hand-off, below)."""
    from mbmon.commands.common import Progress
    from mbmon.sources.files import is_stream_input

    paths = _input_paths(args)
    check_outputs(args.write, paths)
    check_rotation(args)
    view, flt = view_and_filter(args)
    annotator = make_annotator(args.profile)
    for path, given in zip(paths, args.file or [args.rtu_raw], strict=True):
        if not os.path.exists(path):
            err(f"{path}: no such file")
            return EXIT_BAD_INPUT
        if not args.rtu_raw and not is_stream_input(path) and _looks_like_mcap(path):
            err(f"{path} is an MCAP log, not a capture: try 'mbmon replay {given}'")
            return EXIT_BAD_INPUT
    progress = [Progress(f"reading {Path(path).name}") for path in paths]
    try:
        sources = _sources(args, paths, progress)
        # ---- the compiled core's hand-off (mbmon/commands/read_core.py): it takes the
        # whole input when it covers it (one capture file, the options it knows), or
        # declines before writing a byte and the sources below read the input
        done = core_hand_off(sources, args, view, flt, annotator)
        if done is not None:
            return done
        return _read_with_pipeline(args, sources, view, flt, annotator)
    finally:
        for bar in progress:
            bar.close()


def _input_paths(args: argparse.Namespace) -> list[str]:
    """The inputs of ``read`` (``FILE ...`` or ``--rtu-raw FILE``; ``-`` is stdin)."""
    if args.rtu_raw and args.file:
        raise UsageError("give either FILE or --rtu-raw FILE, not both")
    if not args.rtu_raw and not args.file:
        raise UsageError("read needs a FILE (pcap/pcapng) or --rtu-raw FILE")
    given: list[str] = [args.rtu_raw] if args.rtu_raw else list(args.file)
    if given.count("-") > 1:
        raise UsageError("stdin (-) can be read once")
    return ["/dev/stdin" if path == "-" else path for path in given]  # a pipe: never seeks


def _sources(args: argparse.Namespace, paths: list[str], progress: list[Any]) -> list[Any]:
    """One source per input, read one after another: a raw RTU dump, or a capture
    (pcap, pcapng, gzip, 5View) through the dissector; neither is opened yet."""
    from mbmon.sources.files import CaptureFileSource, RawRtuSource
    from mbmon.sources.pcapfile import CaptureConfig

    if args.rtu_raw:
        return [RawRtuSource(paths[0])]
    config = CaptureConfig(
        tcp_ports=frozenset({502, *args.port}),
        rtu_ports=frozenset(args.rtu_port),
        detect=not args.no_detect,
    )
    return [
        CaptureFileSource(path, config, progress=bar)
        for path, bar in zip(paths, progress, strict=True)
    ]


def _read_with_pipeline(
    args: argparse.Namespace, sources: list[Any], view: Any, flt: Any, annotator: Any
) -> int:
    """``read`` by the reference pipeline through the hub: the sources opened (a bad
    input is one line, before any output), then logs, the screen and the summary
    (``-c`` behind the filters), then ``run_sources``. A signal at any instant ends
    it alike: the logs finished, the summary so far, 128 + the signal."""
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sinks.base import SinkError
    from mbmon.sinks.summary import Summary
    from mbmon.sources.base import SourceError, run_sources

    hub = Hub(Pipeline(annotator, PipelineConfig(timeout=args.timeout, baudrate=args.baud)))
    summary = None if args.quiet else Summary(view if args.robot else None)
    live = any(source.mode == "stream" for source in sources)
    gate = open_trigger(args)  # --trigger: the logs and the screen see only its windows
    logs: list[Any] = []
    interrupted = attached = False
    try:
        for source in sources:
            source.open(hub)
        logs = open_logs(
            args.write,
            log_context(args, [source.name for source in sources], view, annotator),
            args,
        )
        attach_outputs(
            hub,
            logs=logs,
            screen=_screen(args, view, flt, live),
            summary=summary,
            budget=FrameBudget(args.count, hub.enough, flt, view) if args.count else None,
            gate=gate,
        )
        attached = True
        run_sources(hub, sources)  # a pipe may stall: the hub ticks meanwhile
    except (SourceError, SinkError) as exc:
        err(str(exc))
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        interrupted = True
    finally:
        for source in sources:
            source.stop()
        hub.close()
        for sink in () if attached else logs:  # a signal came before the hub had them
            sink.close()
    if summary is not None:
        report(summary, capture_stats(sources), args, timed=not args.rtu_raw)
    if interrupted:
        failed = {name for name, _why in hub.failures}
        for sink in logs:
            name = getattr(sink, "path", None)
            if name is not None and str(name) not in failed:
                err(f"interrupted; {name} was finished and is complete up to here")
    elif hub.errors:
        err(hub.errors[-1])
    return exit_status(hub, interrupted=interrupted)


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
