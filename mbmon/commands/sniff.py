"""``mbmon sniff``: passive live capture of Modbus/TCP on a network interface, or of
Modbus RTU on one or two RS485 taps, through the one hub and pipeline.

Wiring only (DESIGN): options (:mod:`~mbmon.commands.options`) → a source of
:mod:`mbmon.sources.base`'s contract and the outputs in the one order
(:func:`~mbmon.commands.listeners.attach_outputs`, ``-c`` in front) → the hub's
loop until Ctrl-C or SIGTERM (:func:`~mbmon.commands.ending.stop_on_signals`: the
hub drains and closes every log) → a summary on stderr → one exit status.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any

from mbmon.sources import DEFAULT_BAUD

if TYPE_CHECKING:
    from mbmon.hub import Hub
    from mbmon.sources.base import Source

_EPILOG = """\
examples:
  mbmon sniff eth0                          Modbus/TCP on port 502, and on any TCP port where
                                            the bytes are Modbus (live monitor on a terminal)
  mbmon sniff -i eth0 --port 1502 -w cell.mcap   only ports 502 and 1502, and an MCAP log
  mbmon sniff eth0 --robot 192.168.0.10 --profile hrss   the robot's labels and HRSS meaning
  mbmon sniff lo -f 'tcp port 5020' --port 5020 -c 10    a BPF filter, stop after 10 frames
  mbmon sniff eth0 --fc 6,16 --address 200-251 -c 20     only writes to R200..R251, 20 of them
  mbmon sniff --list                        the interfaces there are
  mbmon sniff --serial /dev/ttyUSB0 --baud 19200 --parity E   an RS485 bus (RTU)
  mbmon sniff --serial /dev/ttyUSB0 --serial /dev/ttyUSB1    two one-direction taps
  mbmon sniff eth0 --profile hrss --foxglove   live in Foxglove at ws://127.0.0.1:8765

needs root, or CAP_NET_RAW and CAP_NET_ADMIN on the Python binary (network);
read access to the serial port (serial). The filters (--unit, --fc, --address,
--since, --until, --grep) choose what is shown and what -c counts; -w logs keep
everything up to the end (or up to the N-th frame shown, with -c).
Ctrl-C or SIGTERM ends the capture and finishes the logs; a summary (as `read`
gives, plus kernel drops or bus health) goes to stderr (-q: none).
"""
_EXIT = "exit status: 0 ok, 1 capture could not start or an output failed, 2 usage\n"


def register(sub: Any) -> None:
    """Add the ``sniff`` subparser to ``sub``."""
    import textwrap

    from mbmon.commands.common import (
        add_capture_run_options,
        add_count_option,
        add_foxglove_option,
        add_interface_options,
        add_output_options,
        add_serial_tap_options,
        add_view_options,
    )
    from mbmon.filters import TIMES_HELP, add_filter_options
    from mbmon.timefmt import add_time_option

    p = sub.add_parser(
        "sniff",
        help="capture live Modbus traffic: a network interface or an RS485 bus",
        description="Watch live Modbus traffic passively and show every ADU as the robot's\n"
        "Modbus Monitor does, with its meaning: Modbus/TCP on a network interface (span\n"
        "port, tap, or this host), or Modbus RTU on a serial RS485 tap (docs/sniffing.md).",
        epilog=_EPILOG + textwrap.fill(TIMES_HELP, 80) + "\n" + _EXIT,  # --since: 'times'
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("iface", nargs="?", metavar="IFACE", help="network interface (e.g. eth0, lo)")
    add_interface_options(p)
    add_serial_tap_options(p)
    run = add_capture_run_options(p, add_count_option)
    add_foxglove_option(run)
    add_view_options(p)
    add_output_options(p)
    add_time_option(p)
    add_filter_options(p)
    p.add_argument(
        "--debug-core",
        action="store_true",
        help="say on stderr whether the compiled core runs the capture, or why not",
    )
    p.set_defaults(func=run_sniff)


def run_sniff(args: argparse.Namespace) -> int:
    """``mbmon sniff``: options → source and listeners → the hub's loop until Ctrl-C,
    SIGTERM or the ``-c``-th frame → summary → exit status (a signal is its normal end)."""
    from mbmon.commands.common import (
        EXIT_BAD_INPUT,
        EXIT_OK,
        err,
        exit_status,
        filter_text,
        make_annotator,
        run_live,
        stop_on_signals,
        view_and_filter,
    )
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sources.base import run_sources

    if args.list:  # the interfaces there are, one a line
        from mbmon.sources.sniff import list_interfaces

        print("".join(f"{name:16} {desc}\n" for name, desc in list_interfaces()), end="")
        return EXIT_OK
    view, flt = view_and_filter(args)
    source = _source(args, _core_output(args, view, flt))
    annotator = make_annotator(args.profile)
    baud = getattr(source, "settings", None)
    config = PipelineConfig(timeout=args.timeout, baudrate=baud.baudrate if baud else None)
    hub = Hub(Pipeline(annotator, config))
    stop_requested = threading.Event()

    def stop() -> None:
        stop_requested.set()
        hub.stop()

    if not _open_source(source, hub):  # before any output: a failure leaves no files
        return EXIT_BAD_INPUT
    if not args.quiet:  # before the live screen takes the terminal
        err(f"sniffing {source.name} ({source.describe()}); Ctrl-C to stop")
    ctx = _context(args, source, view, annotator)
    wired = _attach_outputs(args, hub, source, ctx, flt, annotator, stop)
    if wired is None:
        source.stop()
        return EXIT_BAD_INPUT
    monitor, summary = wired
    started = time.time()
    with stop_on_signals(lambda n: stop()):
        try:
            run_live(
                monitor,
                partial(run_sources, hub, [source], stop_requested),
                stop,
                ctx=ctx,
                submit=hub.submit,
                display_filter=filter_text(args),
            )
        finally:
            source.stop()
            hub.close()
    live = getattr(source, "live", None)
    if live is not None and summary is not None:
        from mbmon.core.live import add_counts

        add_counts(summary, live.counts())
    if not args.quiet:
        _summary(args, summary, source, time.time() - started)
    return exit_status(hub, until_signal=True)


def _core_output(args: argparse.Namespace, view: Any, flt: Any) -> Any:
    """How the compiled core writes the run's lines (:class:`~mbmon.sources.sniff.CoreOutput`),
    or ``None`` when the options keep the run off the core (``--debug-core`` says why)."""
    from mbmon.commands.common import err
    from mbmon.commands.screen import _interactive
    from mbmon.core.live import decline_for_sniff

    console = not args.quiet and (args.json or getattr(args, "plain", False) or not _interactive())
    iface = args.interface or args.iface
    why = decline_for_sniff(args, interface=bool(iface), console=console, flt=flt)
    buffer = None
    if why is None:
        from mbmon.sinks.console import utf8_buffer

        buffer = utf8_buffer(sys.stdout)
        if buffer is None:
            why = "stdout is not UTF-8"
    if getattr(args, "debug_core", False):
        err(
            "core: "
            + ("the compiled core runs the capture" if why is None else f"declined ({why})")
        )
    if why is None and buffer is not None:
        from mbmon.sinks.console import RawStdout
        from mbmon.sources.sniff import CoreOutput

        raw = RawStdout(buffer)
        return CoreOutput(view, args.json, args.timeout, raw.write, raw.flush)
    return None


def _source(args: argparse.Namespace, core: Any = None) -> Any:
    """The source the options name (usage errors first, and the outputs checked
    against it): an interface, or the serial bus of one or two taps; ``core``: how
    the compiled core writes the lines of an interface's capture, or ``None``."""
    from mbmon.commands.common import UsageError, check_outputs, check_rotation

    iface = args.interface or args.iface
    if args.interface and args.iface and args.interface != args.iface:
        raise UsageError("give the interface once (IFACE or -i IFACE)")
    if iface and args.serial:
        raise UsageError("sniff either a network interface or --serial ports, not both")
    if not iface and not args.serial:
        raise UsageError("sniff needs an interface (IFACE or -i IFACE), or --serial PORT")
    if len(args.serial) > 2:
        raise UsageError("at most two --serial taps (one per direction)")
    if iface and (args.baud is not None):
        raise UsageError("--baud is for --serial")
    check_outputs(args.write, args.serial)  # before the capture opens: no half start
    check_rotation(args)
    if args.serial:
        from mbmon.sources.serial import SerialSettings
        from mbmon.sources.serialbus import SerialBusSource

        line = SerialSettings(args.baud or DEFAULT_BAUD, args.parity, args.stopbits, args.bytesize)
        return SerialBusSource(args.serial, line, merge_window=args.merge_window)
    from mbmon.sources.pcapfile import CaptureConfig
    from mbmon.sources.sniff import InterfaceSource

    config = CaptureConfig(
        tcp_ports=frozenset({502, *args.port}),
        rtu_ports=frozenset(args.rtu_port),
        # live, detection puts every TCP packet through Python: on by default
        # only while no port is named (a named port keeps the kernel filter narrow)
        detect=not (args.no_detect or args.port or args.rtu_port),
    )
    return InterfaceSource(str(iface), config, args.filter, core=core)


def _open_source(source: Source, hub: Hub) -> bool:
    """Open ``source``; on failure say why in one line and return ``False``."""
    from mbmon.commands.common import err, serial_open_error
    from mbmon.sources.base import SourceError
    from mbmon.sources.serialbus import SerialOpenError

    try:
        source.open(hub)
    except SerialOpenError as exc:
        err(serial_open_error(exc.port, exc.error))
        return False
    except SourceError as exc:
        err(str(exc))
        return False
    return True


def _context(args: argparse.Namespace, source: Any, view: Any, annotator: Any) -> Any:
    """The run's :class:`~mbmon.sinks.base.SinkContext` (log metadata, the feed's topics)."""
    from mbmon.commands.common import profile_sources
    from mbmon.sinks.base import SinkContext

    settings = getattr(source, "settings", None)
    return SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=source.name,
        profiles=profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=args.timeout,
        baud=settings.baudrate if settings is not None else None,
    )


def _attach_outputs(
    args: argparse.Namespace,
    hub: Hub,
    source: Any,
    ctx: Any,
    flt: Any,
    annotator: Any,
    stop: Callable[[], None],
) -> tuple[Any, Any] | None:
    """Open the outputs and attach them: ``-c`` first, then the logs (the Foxglove feed,
    ``-w``), the screen behind the filters, the summary, the monitor's figures.
    Returns ``(monitor, summary)``, or ``None`` after saying why one could not open
    (those already open are closed)."""
    from mbmon.commands.common import (
        Figures,
        FrameBudget,
        attach_outputs,
        err,
        open_console,
        open_foxglove,
        open_logs,
        open_trigger,
    )
    from mbmon.sinks.base import SinkError
    from mbmon.sinks.select import Selection
    from mbmon.sinks.summary import Summary

    gate = open_trigger(args)  # --trigger: the logs and the screen see only its windows
    view = ctx.view
    logs: list[Any] = []
    try:
        feed = open_foxglove(args, ctx)  # first: it may exit before any file is opened
        logs += [feed] if feed is not None else []
        logs += open_logs(args.write, ctx, args)  # closes its own on failure
        console, monitor = open_console(
            args, view, title=f"mbmon sniff {source.name}", annotator=annotator
        )
    except (SinkError, SystemExit) as exc:
        for out in logs:
            out.close()
        if isinstance(exc, SystemExit):
            raise
        err(str(exc))
        return None
    screen = console
    if console is not None and flt.active and monitor is None:
        # the filters choose what is shown; logs (and the monitor) keep everything
        screen = Selection([console], view, flt)
    budget = None
    if args.count:

        def enough() -> None:  # the N-th frame: no more input, no closing figures
            stop()
            hub.enough()

        budget = FrameBudget(args.count, enough, flt, view)
    summary = None if args.quiet else Summary(view if args.robot else None)
    attach_outputs(hub, logs=logs, screen=screen, summary=summary, budget=budget, gate=gate)
    if monitor is not None:
        hub.add_listener(Figures(monitor, source.stats))
    return monitor, summary


def _summary(args: argparse.Namespace, summary: Any, source: Any, elapsed: float) -> None:
    """The closing summary on stderr (not with ``-q``): what the source saw (kernel
    counters and the dissector, or the serial reads and bus health) and the records'
    counts in the words of ``read``'s summary (:class:`~mbmon.sinks.summary.Summary`)."""
    lines = [f"mbmon: sniffed {source.name} for {elapsed:.1f} s"]
    lines.extend("  " + line for line in source.summary())
    detected = getattr(source, "detected", None)
    if detected is not None:
        from mbmon.commands.read import detected_lines

        lines.extend("  " + line for line in detected_lines(detected()))
    lines.extend("  " + line for line in summary.text().splitlines())
    if args.robot and summary.streams and not summary.robot_seen:
        lines.append(f"  warning: the robot {args.robot} (--robot) appears in no stream")
    print("\n".join(lines), file=sys.stderr)
