"""``mbmon sniff``: passive live capture of Modbus/TCP on a network interface, or of
Modbus RTU on one or two RS485 taps, through the one hub and pipeline.

Wiring only; the options, filters (:class:`~mbmon.sinks.select.Selection` in
front of what is shown), ``-c`` and summary (:class:`~mbmon.sinks.summary.Summary`)
are ``read``'s. Network: a :class:`~mbmon.sources.sniff.PacketCapture` reader
thread submits packet batches to the hub; the packet dissector (a hub ticker)
runs in the hub's thread. Serial: one :class:`~mbmon.sources.serial.SerialTap`
thread per port puts chunks of one bus stream (two taps are merged by
timestamp in a :class:`~mbmon.sources.serial.TimeMerge` ticker) and
:class:`~mbmon.sources.serial.BusHealth` watches the bus. The main thread runs
``hub.run``; Ctrl-C and SIGTERM stop it, the hub finishes the pipeline and closes
every listener (the MCAP log is complete), and a summary goes to stderr.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from functools import partial
from typing import Any

from mbmon.sources import DEFAULT_BAUD

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
    shows five writes. Everything up to the N-th counted frame reaches the
    outputs behind it (:class:`_Limited`), nothing after it.
    """

    name = "count"

    def __init__(self, count: int, stop: Any, flt: Any = None, view: Any = None) -> None:
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

        return passes(flt, record, self._view)

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
    from mbmon.commands.common import (
        EXIT_BAD_INPUT,
        EXIT_OK,
        Figures,
        UsageError,
        check_outputs,
        check_rotation,
        filter_text,
        make_annotator,
        open_console,
        open_foxglove,
        open_log,
        open_trigger,
        run_live,
        view_and_filter,
    )
    from mbmon.commands.common import profile_sources as _profile_sources
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sinks.base import SinkContext, SinkError
    from mbmon.sinks.select import Selection
    from mbmon.sinks.summary import Summary

    if args.list:
        from mbmon.sources.sniff import list_interfaces

        for name, desc in list_interfaces():
            print(f"{name:16} {desc}")
        return EXIT_OK
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
    gate = open_trigger(args)  # --trigger: the logs and the screen see only its windows

    serial = bool(args.serial)
    baud = (args.baud or DEFAULT_BAUD) if serial else None
    view, flt = view_and_filter(args)
    annotator = make_annotator(args.profile)
    pipeline = Pipeline(annotator, PipelineConfig(timeout=args.timeout, baudrate=baud))
    hub = Hub(pipeline)
    stop_requested = threading.Event()

    def stop() -> None:
        stop_requested.set()
        hub.stop()

    source_name = "+".join(args.serial) if serial else str(iface)
    ctx = SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=source_name,
        profiles=_profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=args.timeout,
        baud=baud,
    )

    # ---- the source (opened before any output, so a failure leaves no files behind)
    capture: Any = None
    taps: list[Any] = []
    health: Any = None
    dissector: Any = None
    if serial:
        from mbmon.model import Chunk, Direction, Event, EventKind, Transport
        from mbmon.sources.serial import BusHealth, SerialSettings, SerialTap, TimeMerge

        settings = SerialSettings(baud or DEFAULT_BAUD, args.parity, args.stopbits, args.bytesize)
        # a reader thread stamps a read when it holds the GIL again: the default 5 ms
        # switch interval would blur read times (and the gap figures) by up to 5 ms
        sys.setswitchinterval(0.001)
        stream = hub.new_stream(Transport.RTU, source_name, source_name)
        bus = Direction.BUS

        def notice(ts: float, message: str) -> None:
            hub.put(Event(ts, stream, EventKind.NOTICE, {"message": message}))

        if len(args.serial) == 1:

            def deliver(ts: float, data: bytes) -> None:
                hub.put(Chunk(ts, stream, bus, data))

        else:
            merge = TimeMerge(args.merge_window)
            hub.add_ticker(merge)

            def deliver(ts: float, data: bytes) -> None:
                chunk = Chunk(ts, stream, bus, data)
                hub.submit(lambda: merge.add(chunk))

        for port in args.serial:
            tap = SerialTap(port, settings, deliver, notice)
            try:
                tap.open()
            except OSError as exc:
                for t in taps:
                    t.stop()
                from mbmon.commands.common import serial_open_error

                print(f"mbmon: {serial_open_error(port, exc)}", file=sys.stderr)
                return EXIT_BAD_INPUT
            taps.append(tap)
        health = BusHealth(stream, settings, hub.put)
    else:
        from mbmon.sources.pcapfile import CaptureConfig
        from mbmon.sources.sniff import (
            CaptureSetupError,
            PacketCapture,
            capture_filter,
            dissect_batch,
            open_dissector,
        )

        config = CaptureConfig(
            tcp_ports=frozenset({502, *args.port}),
            rtu_ports=frozenset(args.rtu_port),
            # live, detection puts every TCP packet through Python: on by default
            # only while no port is named (a named port keeps the kernel filter narrow)
            detect=not (args.no_detect or args.port or args.rtu_port),
        )
        bpf = args.filter or capture_filter(config)
        dissector = open_dissector(config, hub.new_stream, bus_name=str(iface))
        hub.add_ticker(dissector)

        def deliver_batch(batch: list[tuple[float, int, bytes]]) -> None:
            hub.submit(partial(dissect_batch, dissector, batch))

        def capture_failed(message: str) -> None:
            from mbmon.model import Event, EventKind

            hub.put(Event(time.time(), None, EventKind.NOTICE, {"message": message}))
            stop()

        capture = PacketCapture(str(iface), bpf, deliver_batch, on_error=capture_failed)
        try:
            capture.open()
        except CaptureSetupError as exc:
            print(f"mbmon: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT

    def figures() -> dict[str, Any]:
        if capture is not None:  # the dissector knows connections picked up mid-stream too
            return {
                "open connections": dissector.stats()["open_connections"],
                "kernel drops": capture.kernel_stats().drops,
            }
        return health.screen_figures()

    if not args.quiet:  # before the live screen takes the terminal
        what = f"filter: {capture.bpf}" if capture is not None else health.settings.text()
        print(f"mbmon: sniffing {source_name} ({what}); Ctrl-C to stop", file=sys.stderr)
        sys.stderr.flush()

    # ---- outputs
    budget = _Budget(args.count, stop, flt, view) if args.count else None
    outputs: list[Any] = []
    monitor: Any = None
    summary = None if args.quiet else Summary(view if args.robot else None)

    def abandon() -> None:
        for out in outputs:
            out.close()
        for tap in taps:
            tap.stop()
        if capture is not None:
            capture.stop()

    try:
        feed = open_foxglove(args, ctx)  # first: it may exit before any file is opened
        if feed is not None:
            outputs.append(feed)
        console, monitor = open_console(
            args, view, title=f"mbmon sniff {source_name}", annotator=annotator
        )
        attach = outputs.append
        if gate is not None:
            outputs.append(gate)
            attach = gate.add
        if console is not None:  # the filters choose what is shown; logs keep everything
            # (the monitor keeps everything too and starts with them as its display filter)
            shown = flt.active and monitor is None
            attach(Selection([console], view, flt) if shown else console)
        for target in args.write:
            attach(open_log(target, ctx, args))
        if summary is not None:
            outputs.append(summary)
    except SinkError as exc:
        abandon()
        print(f"mbmon: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except SystemExit:
        abandon()
        raise
    if budget is not None:
        hub.add_listener(budget)
        outputs = [_Limited(out, budget) for out in outputs]
    for out in outputs:
        hub.add_listener(out)
    if health is not None:
        hub.add_listener(health)
    if monitor is not None:
        hub.add_listener(Figures(monitor, figures))

    # ---- run
    started = time.time()
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

    def on_signal(signum: int, frame: object) -> None:
        stop()

    for sig in old:
        signal.signal(sig, on_signal)
    try:
        if capture is not None:
            capture.start()
        for tap in taps:
            tap.start()
        run_live(
            monitor,
            partial(hub.run, stop_requested),
            stop,
            ctx=ctx,
            submit=hub.submit,
            display_filter=filter_text(args),
        )
    finally:
        if capture is not None:
            capture.stop()
        for tap in taps:
            tap.stop()
        if not (budget is not None and budget.done):  # the closing figures, in the logs too
            if health is not None:
                hub.feed(health.stats_event(time.time()))
            if capture is not None:
                hub.feed(_capture_stats(capture, time.time()))
        hub.close()
        for sig, handler in old.items():
            signal.signal(sig, handler)

    if not args.quiet:
        _summary(
            args, summary, capture, taps, health, dissector, time.time() - started, source_name
        )
    if any(why != "broken pipe" for _name, why in hub.failures):
        return EXIT_BAD_INPUT
    return EXIT_OK


def _capture_stats(capture: Any, ts: float) -> Any:
    """A STATS event with the capture's kernel counters (``/mbmon/events`` in a log),
    so a log says by itself whether the capture was complete."""
    from mbmon.model import Event, EventKind

    k = capture.kernel_stats()
    info = {
        "interface": capture.iface,
        "packets": capture.packets,
        "kernel_packets": k.packets,
        "kernel_drops": k.drops,
        "complete": k.drops == 0,
    }
    return Event(ts, None, EventKind.STATS, info)


def _summary(
    args: argparse.Namespace,
    summary: Any,
    capture: Any,
    taps: list[Any],
    health: Any,
    dissector: Any,
    elapsed: float,
    source: str,
) -> None:
    """The closing summary on stderr (not with ``-q``): what the source saw (kernel
    counters, dissector, serial reads, bus health) and the records' counts in the
    words of ``read``'s summary (:class:`~mbmon.sinks.summary.Summary`)."""
    lines = [f"mbmon: sniffed {source} for {elapsed:.1f} s"]
    if capture is not None:
        k = capture.kernel_stats()
        lines.append(
            f"  {capture.packets} packets captured; kernel: {k.packets} matched the filter, "
            f"{k.drops} dropped" + (" (capture INCOMPLETE)" if k.drops else "")
        )
        if dissector is not None:
            s = dissector.stats()
            lines.append(
                f"  {s.get('modbus_packets', 0)} Modbus packets, {s.get('streams', 0)} streams, "
                f"{s.get('gaps', 0)} TCP gaps"
            )
            from mbmon.commands.read import detected_lines

            lines.extend("  " + line for line in detected_lines(dissector.detected()))
    for tap in taps:
        lines.append(
            f"  {tap.port}: {tap.reads} reads, {tap.bytes} bytes"
            + (f", lost {tap.losses} times" if tap.losses else "")
        )
    lines.extend("  " + line for line in summary.text().splitlines())
    if health is not None:
        lines.extend("  " + line for line in health.summary())
    if args.robot and summary.streams and not summary.robot_seen:
        lines.append(f"  warning: the robot {args.robot} (--robot) appears in no stream")
    print("\n".join(lines), file=sys.stderr)
