"""``mbmon proxy``: an active Modbus proxy between a client (PLC) and a server (the
robot) that forwards every request and answer, answers like a gateway when the
robot does not, can refuse writes, and shows and logs what passes through the one
hub. Either side may be an RS485 port (Modbus RTU): :mod:`mbmon.proxy.serial`.

Wiring only. The :class:`~mbmon.proxy.engine.ProxyEngine` runs on its own asyncio
loop in a thread (:class:`~mbmon.proxy.engine.ProxyThread`) and hands copies of
the traffic to the hub's thread-safe queue; the main thread runs ``hub.run``
(pipeline, console, ``-w`` logs). Ctrl-C or SIGTERM stops the engine first (its
last events reach the hub), then the hub finishes and closes every listener,
and a summary goes to stderr.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from typing import Any

_EPILOG = """\
examples:
  mbmon proxy --upstream 192.168.0.10:502
      listen on 127.0.0.1:1502, forward to the robot, print every ADU with the
      robot's labels (the upstream is the robot unless --robot says otherwise)
  mbmon proxy --upstream robot:502 --listen 0.0.0.0:502 -w cell.mcap --profile hrss
      take the robot's place on the cell network (all interfaces, port 502: both
      only because they are asked for) and log to MCAP with HRSS meaning
  mbmon proxy --upstream robot:502 --read-only --allow-write hr:200-251 -q -w audit.mcap
      refuse every write except R200..R251 (exception 01), audit refusals in the log
  mbmon proxy --upstream robot:502 --share-upstream --allow-from 10.0.0.0/24
      many clients over one robot connection; only clients of 10.0.0.0/24
  mbmon proxy --upstream-serial /dev/ttyUSB0 --baud 19200 --parity E
      Modbus/TCP clients reach an RTU slave on RS485 (one request at a time)
  mbmon proxy --listen-serial /dev/ttyUSB0 --upstream-serial /dev/ttyUSB1 -w rs485.mcap
      in the middle of an RS485 link (master on USB0, slave on USB1)

listening: 127.0.0.1:1502 by default. Other interfaces and port 502 are used only
when --listen names them explicitly (e.g. --listen 0.0.0.0:502).
gateway rules: upstream down -> exception 0x0A; no answer in --timeout -> 0x0B
(then, with one upstream connection per client, that connection is renewed so its
late answer can never reach a later request); the client stays connected; late
answers are dropped and logged; answers go on as their bytes arrive, unchanged
(an unknown transaction id too; --share-upstream drops what it cannot route); an
RTU master (--listen-serial) gets silence instead, as from an RTU slave (docs/proxy.md).
screen: the live monitor on a terminal; --plain, --json or a pipe: one line per record.
write specs: hr:100  hr:200-251  coil:0-7  unit:2  unit:2,hr:100-110 ; --deny-write
always wins; with --read-only or any --allow-write only allowed writes pass; with any
guard option a write whose byte count, quantity and length disagree (or whose range
runs past 0xFFFF) is refused as malformed. --read-only is an allow-list of known
reads; --allow-fc CODE[/SUB] opens one more (e.g. --allow-fc 8/1 --allow-fc 65-72).
forwarding: a TCP proxy forwards in a process of its own, on uvloop when installed
(MBMON_EVENT_LOOP=asyncio: asyncio's own loop); TCP keepalive finds vanished peers.
exit status: 0 ok, 1 cannot listen or an output failed, 2 usage
"""

DEFAULT_LISTEN = ("127.0.0.1", 1502)

#: The interpreter's thread switch interval while the proxy runs (default 5 ms).
SWITCH_INTERVAL = 0.0002


def register(sub: Any) -> None:
    """Add the ``proxy`` subparser to ``sub``."""
    from mbmon.commands.common import (
        add_foxglove_option,
        add_live_options,
        add_output_options,
        add_view_options,
        exception_code,
        positive_int,
    )
    from mbmon.commands.common import positive as _positive
    from mbmon.sources import DEFAULT_BAUD

    p = sub.add_parser(
        "proxy",
        help="forward Modbus/TCP between a client and the robot, and show it",
        description="An active Modbus/TCP proxy: clients connect to it, it forwards every "
        "request to the upstream server (the robot) and every answer back, unchanged, and "
        "shows and logs what passes as the robot's Modbus Monitor does. When the upstream "
        "is down or silent it answers like a Modbus gateway (exceptions 0x0A/0x0B); it can "
        "refuse writes (--read-only, --allow-write, --deny-write) and clients (--allow-from).",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    net = p.add_argument_group("network")
    net.add_argument(
        "--upstream",
        metavar="HOST:PORT",
        help="the Modbus/TCP server to forward to (the robot), e.g. 192.168.0.10:502 "
        "(or --upstream-serial)",
    )
    net.add_argument(
        "--listen",
        metavar="ADDR:PORT",
        help="where clients connect (default 127.0.0.1:1502, loopback only); other "
        "interfaces or port 502 only when named here, e.g. 0.0.0.0:502; a bare PORT "
        "means 127.0.0.1:PORT; port 0 picks a free port (printed)",
    )
    net.add_argument(
        "--timeout",
        type=_positive,
        default=3.0,
        metavar="S",
        help="answer 0x0B when the upstream has not answered in S seconds; also how long "
        "a client may stay half-way through a request or not read (default 3)",
    )
    net.add_argument(
        "--share-upstream",
        action="store_true",
        help="all clients over one upstream connection, transaction ids remapped (for "
        "servers that accept few connections); default: one upstream connection per "
        "client, transaction ids untouched",
    )
    ser = p.add_argument_group("serial (RS485, Modbus RTU; docs/proxy.md)")
    ser.add_argument(
        "--upstream-serial",
        metavar="PORT",
        help="the upstream is an RTU slave on this serial port (TCP->RTU, or RTU<->RTU "
        "with --listen-serial): one request at a time on the bus, clients served in turn",
    )
    ser.add_argument(
        "--listen-serial",
        metavar="PORT",
        help="the client is an RTU master on this serial port; the proxy answers as its "
        "slave (RTU->TCP, or RTU<->RTU with --upstream-serial); it gets silence, not "
        "0x0A/0x0B, when the upstream cannot answer",
    )
    ser.add_argument(
        "--baud",
        type=positive_int,
        default=DEFAULT_BAUD,
        metavar="N",
        help=f"baud rate ({DEFAULT_BAUD})",
    )
    ser.add_argument("--parity", choices=("N", "E", "O"), default="N", help="parity (N)")
    ser.add_argument("--stopbits", type=int, choices=(1, 2), default=1, help="stop bits (1)")
    guard = p.add_argument_group("guard")
    guard.add_argument(
        "--read-only",
        action="store_true",
        help="only what is known to be a read passes: FC 01-04 07 0B 0C 11 14 18, 2B/0E "
        "and Diagnostics 08 sub-functions 00, 02, 0B-12 (counters); every write (05 06 0F "
        "10 15 16, the write of 17) except what --allow-write allows and every other code "
        "(08/01 restart, 08/04 listen-only, user-defined 0x41-0x48, 0x64-0x6E...) is refused "
        "and audited unless --allow-fc opens it",
    )
    guard.add_argument(
        "--allow-fc",
        action="append",
        default=[],
        metavar="CODE[/SUB]",
        help="with --read-only: let a code that does not write through (repeatable): "
        "65, 65-72, 0x41, 8/1 (a Diagnostics sub-function), 0x2B/0x0D (an MEI type); "
        "decimal or 0x hex",
    )
    guard.add_argument(
        "--allow-write",
        action="append",
        default=[],
        metavar="SPEC",
        help="writes allowed (hr:100, hr:200-251, coil:0-7, unit:2, unit:2,hr:0-9); with "
        "any --allow-write, writes not covered are refused (repeatable)",
    )
    guard.add_argument(
        "--deny-write",
        action="append",
        default=[],
        metavar="SPEC",
        help="writes refused whatever else allows them (repeatable)",
    )
    guard.add_argument(
        "--guard-exception",
        type=exception_code,
        default=0x01,
        metavar="N",
        help="exception code a refused write is answered with (default 1, Illegal Function)",
    )
    guard.add_argument(
        "--allow-from",
        action="append",
        default=[],
        metavar="CIDR",
        help="accept clients only from these networks (repeatable; default: any)",
    )
    screen = p.add_argument_group("screen")
    add_live_options(screen)
    add_foxglove_option(screen)
    add_view_options(p)
    add_output_options(p)
    # the proxy's start-up line (its port) and its summary are what a supervisor and
    # an audit need: -q silences the records only (docs/proxy.md)
    quiet = p._option_string_actions["--quiet"]
    quiet.help = (
        "print no records (the start-up line and the summary still go to stderr; use with -w)"
    )
    p.set_defaults(func=run, robot="upstream")


def run(args: argparse.Namespace) -> int:
    """Start the engine, run the hub until Ctrl-C/SIGTERM, print the summary."""
    from mbmon.commands.common import (
        EXIT_BAD_INPUT,
        EXIT_OK,
        Figures,
        UsageError,
        check_rotation,
        make_annotator,
        open_console,
        open_foxglove,
        open_log,
        parse_address,
        profile_sources,
        run_live,
    )
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.proxy.config import ProxyConfig, endpoint
    from mbmon.proxy.guard import ClientFilter, Guard, GuardSpecError
    from mbmon.proxy.runner import attach_engine, unresolved
    from mbmon.sinks.base import SinkContext, SinkError

    if (args.upstream is None) == (args.upstream_serial is None):
        raise UsageError("give the upstream once: --upstream HOST:PORT or --upstream-serial PORT")
    if args.listen is not None and args.listen_serial is not None:
        raise UsageError("listen either on --listen ADDR:PORT or on --listen-serial PORT")
    if args.allow_from and args.listen_serial is not None:
        raise UsageError("--allow-from is for TCP clients, not --listen-serial")
    check_rotation(args)
    if args.trigger is not None:
        raise UsageError("--trigger works with read and sniff; the proxy logs everything")
    if args.upstream is not None:
        up_host, up_port = parse_address(args.upstream, "--upstream")
        upstream = endpoint(up_host, up_port)
    else:
        up_host, up_port = "", 0
        upstream = args.upstream_serial
    serial = args.upstream_serial is not None or args.listen_serial is not None
    if args.listen is None:
        listen_host, listen_port = DEFAULT_LISTEN
    else:
        listen_host, listen_port = parse_address(
            args.listen, "--listen", default_host="127.0.0.1", lowest=0
        )
    try:
        guard = Guard.from_options(
            args.read_only,
            args.allow_write,
            args.deny_write,
            args.guard_exception,
            allow_fc=args.allow_fc,
        )
        clients = ClientFilter(args.allow_from)
    except GuardSpecError as exc:
        raise UsageError(str(exc)) from None
    robot = None if args.robot in ("none", "") else args.robot
    if robot == "upstream":
        robot = upstream
    view = View(robot=robot, robot_is_client=args.robot_client)
    annotator = make_annotator(args.profile)
    # the proxy answers 0x0B at --timeout itself: the pipeline waits a little
    # longer, so that answer pairs with its request instead of racing it
    pipe_timeout = args.timeout + 1.0
    baud = args.baud if serial else None
    pipeline = Pipeline(annotator, PipelineConfig(timeout=pipe_timeout, baudrate=baud))
    config = ProxyConfig(
        upstream_host=up_host,
        upstream_port=up_port,
        listen_host=listen_host,
        listen_port=listen_port,
        timeout=args.timeout,
        share_upstream=args.share_upstream or args.upstream_serial is not None,
        upstream_name=args.upstream_serial,
        guard=guard,
        clients=clients,
    )
    ctx = SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=f"proxy {args.listen_serial or endpoint(listen_host, listen_port)} -> {upstream}",
        profiles=profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=pipe_timeout,
        baud=baud,
    )
    factories: dict[str, Any] = {}
    if serial:
        from mbmon.proxy.serial import rtu_front, rtu_upstream
        from mbmon.sources.serial import SerialSettings

        settings = SerialSettings(args.baud, args.parity, args.stopbits)
        if args.upstream_serial is not None:
            factories["upstream"] = rtu_upstream(args.upstream_serial, settings)
        if args.listen_serial is not None:
            factories["front"] = rtu_front(args.listen_serial, settings)
    hub = Hub(pipeline)
    try:
        feed = open_foxglove(args, ctx)  # before any file: a missing SDK leaves nothing behind
        if feed is not None:
            hub.add_listener(feed)
        for target in args.write:
            hub.add_listener(open_log(target, ctx, args))
    except SinkError as exc:
        print(f"mbmon: {exc}", file=sys.stderr)
        hub.close()
        return EXIT_BAD_INPUT
    # the TCP proxy forwards in a process of its own (its own GIL: observation never
    # takes CPU time from forwarding); the serial variants are bound by the bus; the
    # child's pipes need POSIX (pass_fds, the loop's readers on pipes)
    process = not serial and os.name == "posix"
    engine, thread, observer = attach_engine(hub, config, process=process, **factories)
    try:
        address = thread.start()
    except OSError as exc:
        from mbmon.commands.common import listen_error

        text = listen_error(endpoint(listen_host, listen_port), exc, listen_port)
        if serial:
            from mbmon.proxy.serial import SerialOpenError

            if isinstance(exc, SerialOpenError):
                text = exc.strerror or str(exc)
        print(f"mbmon: {text}", file=sys.stderr)
        hub.run(until_idle=True)
        hub.close()
        return EXIT_BAD_INPUT
    # Ctrl-C and SIGTERM stop the engine from now on: before the start-up line, which
    # is what a supervisor (or a test) waits for before it may signal
    signals = [0]

    def _stop(signum: int, frame: object) -> None:
        signals[0] += 1
        thread.stop()  # the engine's last events reach the hub, then it stops the hub
        if signals[0] > 1:
            hub.stop()  # asked twice: do not wait for the engine

    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    if args.upstream_serial is not None:
        mode = f"RTU slave bus {settings.text()}, one request at a time"
    elif args.share_upstream:
        mode = "shared upstream connection"
    else:
        mode = "one upstream connection per client"
    if args.listen_serial is not None:
        where = f"{args.listen_serial} (RTU master side, {settings.text()})"
    else:
        where = endpoint(*address)
    print(
        f"mbmon proxy: listening on {where} -> upstream {upstream} "
        f"({mode}, timeout {args.timeout:g} s, guard {guard.describe()})",
        file=sys.stderr,
        flush=True,
    )
    if args.upstream is not None:
        why = unresolved(up_host, up_port)
        if why is not None:
            # the host may come later (DNS, /etc/hosts): keep running, answer 0x0A
            warning = (
                f"upstream host {up_host!r} does not resolve ({why}): clients get "
                "exception 0x0A until it does; the proxy keeps trying"
            )
            print(f"mbmon proxy: warning: {warning}", file=sys.stderr, flush=True)
            from mbmon.model import Event, EventKind

            hub.put(Event(time.time(), None, EventKind.NOTICE, {"message": warning}))
    # the screen last: the logs are open, and the start-up line is on the terminal
    # before the live monitor takes it
    console, monitor = open_console(
        args, view, title=f"mbmon proxy -> {upstream}", annotator=annotator
    )
    if console is not None:
        hub.add_listener(console)
    if monitor is not None:
        hub.add_listener(Figures(monitor, engine.figures))

    try:
        try:
            run_live(
                monitor, hub.run, lambda: _stop(signal.SIGINT, None), ctx=ctx, submit=hub.submit
            )
        finally:
            thread.stop()
            thread.join(5.0)
            hub.close()
        engine.stats.not_observed = observer.skipped
        print("mbmon proxy: " + engine.stats.summary().replace("\n", "\n  "), file=sys.stderr)
        if getattr(engine, "final", True) is False:
            status = getattr(thread, "returncode", None)
            print(
                f"mbmon: the proxy's forwarding process ended unexpectedly (status {status}); "
                "the counters above are the last it sent",
                file=sys.stderr,
            )
            return EXIT_BAD_INPUT
    finally:  # a late Ctrl-C must not cut the logs' close or the summary short
        for s, handler in old.items():
            signal.signal(s, handler)
    if any(name != "stdout" or why != "broken pipe" for name, why in hub.failures):
        return EXIT_BAD_INPUT
    return EXIT_OK
