"""``mbmon sniff``: passive live capture of Modbus/TCP on a network interface, or of
Modbus RTU on one or two RS485 taps, through the one hub and pipeline.

Wiring only: options → a source (:class:`~mbmon.sources.sniff.InterfaceSource`
for a network interface, :class:`~mbmon.sources.serialbus.SerialBusSource` for
one or two RS485 taps; both implement :mod:`mbmon.sources.base`'s contract) and
listeners (logs first, then the screen behind the filters, then the summary; ``-c``
in front of them) → :func:`~mbmon.sources.base.run_sources` → one exit status.
The main thread runs the hub's loop; Ctrl-C and SIGTERM stop it, the hub finishes
the pipeline and closes every listener (the MCAP log is complete), and a summary
(the source's lines, then ``read``'s counts) goes to stderr.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
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
        add_foxglove_option,
        add_live_options,
        add_output_options,
        add_port_options,
        add_view_options,
    )
    from mbmon.commands.common import positive as _positive
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
    src = p.add_argument_group("network")
    src.add_argument("-i", "--interface", dest="interface", metavar="IFACE", help="as IFACE")
    src.add_argument("--list", action="store_true", help="list the network interfaces and exit")
    src.add_argument(
        "-f",
        "--filter",
        metavar="BPF",
        help="kernel capture filter (tcpdump syntax) instead of the default: 'tcp or "
        "udp port 502' while Modbus is looked for on every TCP port (no --port, "
        "--rtu-port or --no-detect), else 'tcp port 502 or udp port 502' plus those ports",
    )
    add_port_options(src)
    ser = p.add_argument_group("serial (RS485, Modbus RTU)")
    ser.add_argument(
        "--serial",
        action="append",
        default=[],
        metavar="PORT",
        help="serial port of a passive RS485 tap; give it twice for two one-direction "
        "taps merged by timestamp",
    )
    ser.add_argument(
        "--baud", type=int, default=None, metavar="N", help=f"baud rate ({DEFAULT_BAUD})"
    )
    ser.add_argument("--parity", choices=("N", "E", "O"), default="N", help="parity (N)")
    ser.add_argument("--stopbits", type=int, choices=(1, 2), default=1, help="stop bits (1)")
    ser.add_argument("--bytesize", type=int, choices=(5, 6, 7, 8), default=8, help="data bits (8)")
    ser.add_argument(
        "--merge-window",
        type=_positive,
        default=0.05,
        metavar="S",
        help="with two taps: hold reads S seconds to merge them in time order (0.05)",
    )
    run = p.add_argument_group("run")
    run.add_argument(
        "-c",
        "--count",
        type=int,
        default=None,
        metavar="N",
        help="stop after N Modbus frames (those the filters let through)",
    )
    run.add_argument(
        "--timeout",
        type=_positive,
        default=1.0,
        metavar="S",
        help="report a request unanswered after S seconds (default 1.0)",
    )
    add_live_options(run)
    add_foxglove_option(run)
    add_view_options(p)
    add_output_options(p)
    add_time_option(p)
    add_filter_options(p)
    p.set_defaults(func=run_sniff)


# --------------------------------------------------------------------------- -c COUNT


class _Budget:
    """Counts frame records for ``-c``; the first listener, so it cuts each batch first.

    With filters (``--fc``, ``--unit``, ...) only the frames they let through
    count, as with tcpdump's ``-c`` behind its filter: ``sniff --fc 16 -c 5``
    shows five writes; events never count. Everything up to the N-th counted
    frame reaches the outputs behind it (:class:`_Limited`), nothing after it.
    """

    name = "count"

    def __init__(self, count: int, stop: Callable[[], Any], flt: Any = None, view: Any = None):
        self.left = count
        self._stop = stop
        self._filter = flt if flt is not None and flt.active else None
        self._view = view
        self.done = False
        self._batch: list[Any] | None = None
        self._cut: list[Any] = []

    def _counts(self, record: Any) -> bool:
        if record.frame is None:
            return False
        flt = self._filter
        if flt is None:
            return True
        from mbmon.sinks.select import passes

        return bool(passes(flt, record, self._view))

    def on_records(self, records: list[Any]) -> None:
        if self.done:
            self._batch, self._cut = records, []
            return
        keep = len(records)
        for i, record in enumerate(records):
            if self._counts(record):
                self.left -= 1
                if self.left <= 0:
                    keep = i + 1
                    self.done = True
                    self._stop()
                    break
        self._batch, self._cut = records, records[:keep]

    def allowed(self, records: list[Any]) -> list[Any]:
        return self._cut if records is self._batch else ([] if self.done else records)


class _Limited:
    """An output behind the ``-c`` budget: it sees nothing after the N-th frame."""

    def __init__(self, inner: Any, budget: _Budget) -> None:
        from mbmon.hub import hooks_of

        self.inner = inner
        self.budget = budget
        self.name = getattr(inner, "name", None) or getattr(inner, "path", None)
        self._hooks = hooks_of(inner)

    def on_records(self, records: list[Any]) -> None:
        records = self.budget.allowed(records)
        if records:
            self._hooks.records(records)

    def on_chunk(self, chunk: Any) -> None:
        if not self.budget.done:
            self._hooks.item(chunk)

    def on_event(self, event: Any) -> None:
        if not self.budget.done:
            self._hooks.item(event)

    def on_tick(self, now: float) -> None:
        self._hooks.tick(now)

    def close(self) -> None:
        if self._hooks.close is not None:
            self._hooks.close()


# --------------------------------------------------------------------------- run


def run_sniff(args: argparse.Namespace) -> int:
    """``mbmon sniff``: options → source and listeners → the hub's loop → exit status."""
    from mbmon.commands.common import EXIT_BAD_INPUT, EXIT_OK, make_annotator, view_and_filter
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sources.base import run_sources

    if args.list:
        return _list_interfaces()
    source = _source(args)
    view, flt = view_and_filter(args)
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
        print(f"mbmon: sniffing {source.name} ({source.describe()}); Ctrl-C to stop",
              file=sys.stderr, flush=True)  # fmt: skip
    ctx = _context(args, source, view, annotator)
    wired = _attach_outputs(args, hub, source, ctx, flt, annotator, stop)
    if wired is None:
        source.stop()
        return EXIT_BAD_INPUT
    monitor, summary = wired
    started = time.time()
    from mbmon.commands.common import filter_text, run_live

    with _signals_stop(stop):
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
    if not args.quiet:
        _summary(args, summary, source, time.time() - started)
    if any(why != "broken pipe" for _name, why in hub.failures):
        return EXIT_BAD_INPUT
    return EXIT_OK


def _list_interfaces() -> int:
    """``--list``: the interfaces there are, one a line."""
    from mbmon.sources.sniff import list_interfaces

    for name, desc in list_interfaces():
        print(f"{name:16} {desc}")
    return 0


def _source(args: argparse.Namespace) -> Any:
    """The source the options name (usage errors first, and the outputs checked
    against it): an interface, or the serial bus of one or two taps."""
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
    if args.count is not None and args.count < 1:
        raise UsageError("-c needs a count of at least 1")
    if args.baud is not None and args.baud <= 0:
        raise UsageError(f"bad baud rate {args.baud}")
    if iface and (args.baud is not None):
        raise UsageError("--baud is for --serial")
    check_outputs(args.write, args.serial)  # before the capture opens: no half start
    check_rotation(args)
    if args.serial:
        from mbmon.sources.serial import SerialSettings
        from mbmon.sources.serialbus import SerialBusSource

        settings = SerialSettings(
            args.baud or DEFAULT_BAUD, args.parity, args.stopbits, args.bytesize
        )
        return SerialBusSource(args.serial, settings, merge_window=args.merge_window)
    from mbmon.sources.pcapfile import CaptureConfig
    from mbmon.sources.sniff import InterfaceSource

    config = CaptureConfig(
        tcp_ports=frozenset({502, *args.port}),
        rtu_ports=frozenset(args.rtu_port),
        # live, detection puts every TCP packet through Python: on by default
        # only while no port is named (a named port keeps the kernel filter narrow)
        detect=not (args.no_detect or args.port or args.rtu_port),
    )
    return InterfaceSource(str(iface), config, args.filter)


def _open_source(source: Source, hub: Hub) -> bool:
    """Open ``source``; on failure say why in one line and return ``False``."""
    from mbmon.commands.common import serial_open_error
    from mbmon.sources.base import SourceError
    from mbmon.sources.serialbus import SerialOpenError

    try:
        source.open(hub)
    except SerialOpenError as exc:
        print(f"mbmon: {serial_open_error(exc.port, exc.error)}", file=sys.stderr)
        return False
    except SourceError as exc:
        print(f"mbmon: {exc}", file=sys.stderr)
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
    from mbmon.commands.common import Figures, open_console, open_foxglove, open_log, open_trigger
    from mbmon.sinks.base import SinkError
    from mbmon.sinks.select import Selection
    from mbmon.sinks.summary import Summary

    gate = open_trigger(args)  # --trigger: the logs and the screen see only its windows
    view = ctx.view
    opened: list[Any] = []
    try:
        feed = open_foxglove(args, ctx)  # first: it may exit before any file is opened
        if feed is not None:
            opened.append(feed)
        for target in args.write:
            opened.append(open_log(target, ctx, args))
        console, monitor = open_console(
            args, view, title=f"mbmon sniff {source.name}", annotator=annotator
        )
    except SinkError as exc:
        for out in opened:
            out.close()
        print(f"mbmon: {exc}", file=sys.stderr)
        return None
    except SystemExit:
        for out in opened:
            out.close()
        raise
    if console is not None:  # the filters choose what is shown; logs keep everything
        # (the monitor keeps everything too and starts with them as its display filter)
        opened.append(
            Selection([console], view, flt) if flt.active and monitor is None else console
        )
    outputs: list[Any] = opened
    if gate is not None:
        for out in opened:
            gate.add(out)
        outputs = [gate]
    summary = None if args.quiet else Summary(view if args.robot else None)
    if summary is not None:
        outputs.append(summary)
    if args.count:

        def enough() -> None:  # the N-th frame: no more input, no closing figures
            stop()
            hub.enough()

        budget = _Budget(args.count, enough, flt, view)
        hub.add_listener(budget)
        outputs = [_Limited(out, budget) for out in outputs]
    for out in outputs:
        hub.add_listener(out)
    if monitor is not None:
        hub.add_listener(Figures(monitor, source.stats))
    return monitor, summary


@contextmanager
def _signals_stop(stop: Callable[[], None]) -> Iterator[None]:
    """Inside the block SIGINT and SIGTERM call ``stop()`` (the run ends in order:
    sources stopped, the hub drained and finished, every log closed)."""
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def on_signal(signum: int, frame: object) -> None:
        stop()

    for sig in old:
        signal.signal(sig, on_signal)
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


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
