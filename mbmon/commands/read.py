"""``mbmon read``: a capture file or a raw RTU bus dump through the hub, to the console and logs."""

from __future__ import annotations

import argparse
import itertools
import os
import stat
import sys
import textwrap
from collections.abc import Iterable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from mbmon.commands.common import (
    EXIT_BAD_INPUT,
    EXIT_OK,
    UsageError,
    add_output_options,
    add_port_options,
    add_view_options,
    check_outputs,
    check_rotation,
    err,
    make_annotator,
    open_log,
    open_trigger,
    positive,
    positive_int,
    profile_sources,
    view_and_filter,
)
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
  mbmon read cell.pcap -c 20                   the first 20 records only
  mbmon read cell.pcap --fc 6,16 --address 200-251 -t r
      only writes touching R200..R251, times relative to the first record
  mbmon read cell.pcap -w cell.mcap            also record an MCAP log (Foxglove)
  mbmon read week.pcap -w fault.mcap --trigger 'exception or timeout' --before 30s --after 10s
      keep only 40 s around each fault: one MCAP file per window

output lines: TIME  LABEL  [uUNIT tTID]  FUNCTION-CODE + DATA (hex)  | meaning
a summary goes to stderr at the end (-q: none)
exit status: 0 ok, 1 bad or damaged input (everything before the damage is printed), 2 usage

"""

#: The first bytes of an MCAP file (mbmon's logs).
MCAP_MAGIC = b"\x89MCAP0\r\n"


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
    src.add_argument(
        "-c",
        "--count",
        type=positive_int,
        metavar="N",
        help="stop after N records (like tshark -c)",
    )
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
    """``mbmon read``: every record of the input to the console, the logs and the summary."""
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sinks.base import SinkContext, SinkError
    from mbmon.sinks.console import ConsoleListener
    from mbmon.sinks.select import Selection
    from mbmon.sinks.summary import Summary

    if args.rtu_raw and args.file:
        raise UsageError("give either FILE or --rtu-raw FILE, not both")
    if not args.rtu_raw and not args.file:
        raise UsageError("read needs a FILE (pcap/pcapng) or --rtu-raw FILE")
    path = args.rtu_raw or args.file
    if path == "-":
        path = "/dev/stdin"  # a pipe: the readers never seek
    check_outputs(args.write, [path])
    check_rotation(args)
    view, flt = view_and_filter(args)
    annotator = make_annotator(args.profile)
    pipeline = Pipeline(annotator, PipelineConfig(timeout=args.timeout, baudrate=args.baud))
    from mbmon.commands.common import Progress

    progress = Progress(f"reading {Path(path).name}")
    live = _is_stream_input(path)
    capture_stats: dict[str, Any] = {}

    if not os.path.exists(path):
        err(f"{path}: no such file")
        return EXIT_BAD_INPUT
    if not args.rtu_raw and not (not live and _looks_like_mcap(path)):
        done = _read_with_core(path, args, view, flt, live=live, progress=progress)
        if done is not None:
            progress.close()
            return done
    if args.rtu_raw:
        from mbmon.sources.pcapfile import CaptureError
        from mbmon.sources.rawfile import read_rtu_raw

        try:
            items: Iterable[Any] = read_rtu_raw(path)
        except CaptureError as exc:
            err(str(exc))
            return EXIT_BAD_INPUT
    else:
        from mbmon.sources.pcapfile import CaptureConfig, CaptureError, read_capture

        if not live and _looks_like_mcap(path):
            err(f"{path} is an MCAP log, not a capture: try 'mbmon replay {args.file}'")
            return EXIT_BAD_INPUT
        config = CaptureConfig(
            tcp_ports=frozenset({502, *args.port}),
            rtu_ports=frozenset(args.rtu_port),
            detect=not args.no_detect,
        )
        try:
            items = read_capture(path, config, progress=progress, stats=capture_stats)
            first = next(iter_items := iter(items), None)
        except CaptureError as exc:
            err(str(exc))
            return EXIT_BAD_INPUT
        items = itertools.chain(() if first is None else (first,), iter_items)

    ctx = SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=str(path),
        profiles=profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=args.timeout,
        baud=args.baud,
    )
    hub = Hub(pipeline)
    summary = Summary(view if args.robot else None)
    gate = open_trigger(args)  # --trigger: the logs and the screen see only its windows
    attach = hub.add_listener if gate is None else gate.add
    logs: list[Any] = []
    interrupted = False
    with ExitStack() as stack:
        stack.callback(hub.close)
        stack.callback(progress.close)
        # logs first: a record printed on stdout has reached them when a signal stops the run
        for target in args.write:
            try:
                sink = open_log(target, ctx, args)
            except SinkError as exc:
                err(str(exc))
                return EXIT_BAD_INPUT
            logs.append(sink)
            attach(sink)
        shown = (
            [] if args.quiet else [ConsoleListener(sys.stdout, view, as_json=args.json, live=live)]
        )
        if shown or args.count:
            attach(Selection(shown, view, flt, args.count, on_full=hub.enough))
        if gate is not None:
            hub.add_listener(gate)
        if not args.quiet:
            hub.add_listener(summary)
        try:
            if live:  # a pipe may stall: the hub ticks meanwhile, so logs reach the disk
                from mbmon.sources.pipe import feed_pipe

                feed_pipe(hub, items)
            else:
                hub.run_items(items)
        except KeyboardInterrupt:
            interrupted = True
    if not args.quiet:
        _report(summary, capture_stats, args, timed=not args.rtu_raw)
    if interrupted:
        for sink in logs:
            if sink in hub.listeners or (gate is not None and gate in hub.listeners):
                err(f"interrupted; {getattr(sink, 'path', 'the log')} was finished and is complete "
                    "up to here")  # fmt: skip
        return 130
    if hub.errors:
        err(hub.errors[-1])
        return EXIT_BAD_INPUT
    if any(why != "broken pipe" for _name, why in hub.failures):
        return EXIT_BAD_INPUT
    return EXIT_OK


def _read_with_core(
    path: str, args: argparse.Namespace, view: Any, flt: Any, *, live: bool, progress: Any
) -> int | None:
    """``read`` by the compiled core when it covers the options and the input: its exit
    status; ``None`` when it declined (before writing anything: the Python pipeline
    then reads the input). ``--debug-core`` says which path ran and why."""
    from mbmon import core

    why = core.decline_for_options(args, live=live, flt=flt)
    write = None
    broken: list[bool] = []
    if why is None and not args.quiet:
        from mbmon.sinks.console import utf8_buffer

        buffer = utf8_buffer(sys.stdout)
        if buffer is None:
            why = "stdout is not UTF-8"
        else:

            def write(data: bytes) -> None:
                if broken:
                    return
                try:
                    buffer.write(data)
                except BrokenPipeError:  # the reader went away (| head), as the hub does
                    from mbmon.hub import _quiet_stdout

                    broken.append(True)
                    _quiet_stdout()

    if why is None:
        run = core.read_file(
            path,
            ports=frozenset({502, *args.port}),
            timeout=args.timeout,
            view=view,
            as_json=args.json,
            write=write,
            progress=progress,
            detect=not args.no_detect,
        )
        progress.close()
        why = run.declined
    if why is not None:
        if args.debug_core:
            err(f"core: declined ({why}); the Python pipeline reads the input")
        return None
    if write is not None and not broken:
        try:
            sys.stdout.flush()
        except BrokenPipeError:
            from mbmon.hub import _quiet_stdout

            _quiet_stdout()
    if args.debug_core:
        err("core: the compiled core read the input")
    if not args.quiet:
        from mbmon.sinks.summary import Summary

        summary = Summary(None)
        core.fill_summary(summary, run.counts)
        _report(summary, {}, args, timed=True)
    return EXIT_OK


def _report(
    summary: Any, capture_stats: dict[str, Any], args: argparse.Namespace, *, timed: bool
) -> None:
    """The summary and the hints a user needs after a read, on stderr."""
    try:
        print(summary.text(timed=timed), file=sys.stderr, flush=True)
    except (OSError, ValueError):
        return
    for line in detected_lines(capture_stats.get("detected") or []):
        err(line)
    if summary.frames == 0 and not args.rtu_raw:
        busiest = capture_stats.get("busiest_ports") or []
        ports = ", ".join(f"{proto}/{p} ({n} packets)" for proto, p, n in busiest[:5])
        asked = ", ".join(str(p) for p in sorted({502, *args.port, *args.rtu_port}))
        hint = f"no Modbus found on port {asked}"
        if not args.no_detect:
            hint += " nor by its structure on any other TCP port"
        if ports:
            first = busiest[0][1]
            hint += f"; busiest ports: {ports}; try --port {first} (or --rtu-port {first})"
        err(hint)
    if args.robot and summary.streams and not summary.robot_seen:
        err(f"warning: the robot {args.robot} (--robot) appears in no stream of this capture")


def detected_lines(found: list[tuple[str, int, str, int]]) -> list[str]:
    """One line per port that port detection found (the dissector's
    ``detected()``): the transport, the port, its servers and connections."""
    ports: dict[tuple[str, int], list[tuple[str, int]]] = {}
    for transport, number, server, streams in found:
        ports.setdefault((transport, number), []).append((server, streams))
    lines = []
    for (transport, number), servers in ports.items():
        what = "RTU over TCP" if transport == "rtu-over-tcp" else "Modbus/TCP"
        names = ", ".join(server for server, _ in servers[:3])
        if len(servers) > 3:
            names += f" and {len(servers) - 3} more"
        streams = sum(n for _, n in servers)
        lines.append(
            f"found {what} on port {number} by its structure: {streams} connection"
            f"{'s' if streams != 1 else ''} to {names} (--no-detect turns this off)"
        )
    return lines
