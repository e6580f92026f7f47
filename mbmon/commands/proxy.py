"""``mbmon proxy``: an active Modbus proxy between a client (PLC) and a server (the
robot) that forwards every request and answer, answers like a gateway when the
robot does not, can refuse writes, and shows and logs what passes through the one
hub. Either side may be an RS485 port (Modbus RTU): :mod:`mbmon.proxy.serial`.

Wiring only: the options are checked into a :class:`~mbmon.proxy.plan.ProxyPlan`,
and :func:`~mbmon.proxy.runner.attach_engine` runs the
:class:`~mbmon.proxy.engine.ProxyEngine` on its own asyncio loop (in a child
process for a TCP proxy, else in a thread), which hands copies of the traffic to
the hub's thread-safe queue; the main thread runs ``hub.run`` (pipeline, console,
``-w`` logs). Ctrl-C or SIGTERM stops the engine first (its last events reach the
hub), then the hub finishes and closes every listener, and a summary goes to
stderr.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from typing import Any


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
    from mbmon.proxy.options import EPILOG, add_proxy_options
    from mbmon.sources import DEFAULT_BAUD

    p = sub.add_parser(
        "proxy",
        help="forward Modbus/TCP between a client and the robot, and show it",
        description="An active Modbus/TCP proxy: clients connect to it, it forwards every "
        "request to the upstream server (the robot) and every answer back, unchanged, and "
        "shows and logs what passes as the robot's Modbus Monitor does. When the upstream "
        "is down or silent it answers like a Modbus gateway (exceptions 0x0A/0x0B); it can "
        "refuse writes (--read-only, --allow-write, --deny-write) and clients (--allow-from).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_proxy_options(
        p,
        {"positive": _positive, "positive_int": positive_int, "exception_code": exception_code},
        DEFAULT_BAUD,
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
        UsageError,
        check_rotation,
        listen_error,
        make_annotator,
        parse_address,
        profile_sources,
    )
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.proxy.plan import PlanError, ProxyPlan
    from mbmon.proxy.runner import attach_engine
    from mbmon.sinks.base import SinkContext

    check_rotation(args)
    upstream = None if args.upstream is None else parse_address(args.upstream, "--upstream")
    listen = None
    if args.listen is not None:
        listen = parse_address(args.listen, "--listen", default_host="127.0.0.1", lowest=0)
    try:
        plan = ProxyPlan.from_options(args, upstream, listen)
    except PlanError as exc:
        raise UsageError(str(exc)) from None
    robot = None if args.robot in ("none", "") else args.robot
    view = View(robot=plan.upstream if robot == "upstream" else robot,
                robot_is_client=args.robot_client)  # fmt: skip
    annotator = make_annotator(args.profile)
    # the proxy answers 0x0B at --timeout itself: the pipeline waits a little
    # longer, so that answer pairs with its request instead of racing it
    pipe_timeout = args.timeout + 1.0
    baud = args.baud if plan.serial else None
    hub = Hub(Pipeline(annotator, PipelineConfig(timeout=pipe_timeout, baudrate=baud)))
    ctx = SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=plan.source(),
        profiles=profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=pipe_timeout,
        baud=baud,
    )
    if not _open_logs(hub, args, ctx):
        return EXIT_BAD_INPUT
    engine, thread, observer = attach_engine(
        hub, plan.config, process=plan.process, **plan.factories
    )
    try:
        address = thread.start()
    except OSError as exc:
        print(f"mbmon: {plan.start_error(exc, listen_error)}", file=sys.stderr)
        hub.run(until_idle=True)
        hub.close()
        return EXIT_BAD_INPUT
    return _serve(args, plan, hub, (engine, thread, observer), address, ctx, annotator)


def _open_logs(hub: Any, args: argparse.Namespace, ctx: Any) -> bool:
    """The Foxglove feed and the ``-w`` logs on ``hub`` (logs first: DESIGN rule 7);
    ``False`` (said on stderr, the hub closed) when one cannot be opened."""
    from mbmon.commands.common import open_foxglove, open_log
    from mbmon.sinks.base import SinkError

    try:
        feed = open_foxglove(args, ctx)  # before any file: a missing SDK leaves nothing behind
        if feed is not None:
            hub.add_listener(feed)
        for target in args.write:
            hub.add_listener(open_log(target, ctx, args))
    except SinkError as exc:
        print(f"mbmon: {exc}", file=sys.stderr)
        hub.close()
        return False
    return True


def _serve(
    args: argparse.Namespace,
    plan: Any,
    hub: Any,
    parts: tuple[Any, Any, Any],
    address: tuple[str, int],
    ctx: Any,
    annotator: Any,
) -> int:
    """The started engine's run: signals, the start-up line, the screen, ``hub.run``
    until Ctrl-C/SIGTERM, then the summary and the exit status."""
    from mbmon.commands.common import EXIT_BAD_INPUT, EXIT_OK, Figures, open_console, run_live

    engine, thread, observer = parts
    # Ctrl-C and SIGTERM stop the engine from now on: before the start-up line, which
    # is what a supervisor (or a test) waits for before it may signal
    signals = [0]

    def _stop(signum: int, frame: object) -> None:
        signals[0] += 1
        thread.stop()  # the engine's last events reach the hub, then it stops the hub
        if signals[0] > 1:
            hub.stop()  # asked twice: do not wait for the engine

    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    print(f"mbmon proxy: {plan.startup_line(address)}", file=sys.stderr, flush=True)
    if args.upstream is not None:
        _warn_unresolved(hub, plan.config.upstream_host, plan.config.upstream_port)
    # the screen last: the logs are open, and the start-up line is on the terminal
    # before the live monitor takes it
    console, monitor = open_console(
        args, ctx.view, title=f"mbmon proxy -> {plan.upstream}", annotator=annotator
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


def _warn_unresolved(hub: Any, host: str, port: int) -> None:
    """An upstream host that does not resolve: a warning on stderr and in the log; the
    proxy keeps running and answers 0x0A (the host may come: DNS, /etc/hosts)."""
    from mbmon.model import Event, EventKind
    from mbmon.proxy.runner import unresolved

    why = unresolved(host, port)
    if why is None:
        return
    warning = (
        f"upstream host {host!r} does not resolve ({why}): clients get "
        "exception 0x0A until it does; the proxy keeps trying"
    )
    print(f"mbmon proxy: warning: {warning}", file=sys.stderr, flush=True)
    hub.put(Event(time.time(), None, EventKind.NOTICE, {"message": warning}))
