"""``mbmon proxy``: an active Modbus proxy between a client (PLC) and a server (the
robot) that forwards every request and answer, answers like a gateway when the
robot does not, can refuse writes, and shows and logs what passes through the one
hub. Either side may be an RS485 port (Modbus RTU): :mod:`mbmon.proxy.serial`.

Wiring only: the options are checked into a :class:`~mbmon.proxy.plan.ProxyPlan`;
the proxy is a live source of the hub (:class:`~mbmon.sources.proxy.ProxySource`:
the :class:`~mbmon.proxy.engine.ProxyEngine` on its own asyncio loop, in a child
process for a TCP proxy, else in a thread), which hands copies of the traffic to
the hub's thread-safe queue; the main thread runs ``run_sources`` (pipeline,
console, ``-w`` logs). Ctrl-C or SIGTERM stops the engine first (its last events reach the
hub), then the hub finishes and closes every listener, and a summary goes to
stderr.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from functools import partial
from typing import Any


def register(sub: Any) -> None:
    """Add the ``proxy`` subparser to ``sub``."""
    from mbmon.commands.common import (
        add_foxglove_option,
        add_live_options,
        add_output_options,
        add_serial_line_options,
        add_view_options,
        exception_code,
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
    convert: dict[str, Callable[..., Any]] = {
        "positive": _positive,
        "exception_code": exception_code,
        "serial_line": partial(add_serial_line_options, baud_default=DEFAULT_BAUD),
    }
    add_proxy_options(p, convert)
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
    p.add_argument(
        "--debug-core",
        action="store_true",
        help="say on stderr whether the compiled core observes the traffic, or why not",
    )
    p.set_defaults(func=run, robot="upstream")


def run(args: argparse.Namespace) -> int:
    """``mbmon proxy``: options → a plan → the proxy as a source
    (:class:`~mbmon.sources.proxy.ProxySource`, listening before any output opens) and
    the outputs (logs, then the screen) → ``run_sources`` until Ctrl-C/SIGTERM → the
    summary → one exit status."""
    from mbmon.commands.common import (
        EXIT_BAD_INPUT,
        UsageError,
        check_rotation,
        err,
        exit_status,
        listen_error,
        make_annotator,
        parse_address,
        profile_sources,
    )
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.proxy.plan import PlanError, ProxyPlan
    from mbmon.sinks.base import SinkContext
    from mbmon.sources.proxy import ProxySource, ProxyStartError

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
    source = ProxySource(
        plan.config,
        process=plan.process,
        factories=plan.factories,
        name=plan.source(),
        core=_core_output(args, plan, view, pipe_timeout),
    )
    try:
        source.open(hub)  # it listens when this returns; a failure leaves no files behind
    except ProxyStartError as exc:
        err(plan.start_error(exc.error, listen_error))
        hub.close()
        return exit_status(hub, failed=True, until_signal=True)
    ctx = SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=plan.source(),
        profiles=profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=pipe_timeout,
        baud=baud,
    )
    try:
        logs = _open_logs(args, ctx)
    except BaseException:
        source.stop()
        hub.close()
        raise
    if logs is None:
        source.stop()
        hub.close()
        return EXIT_BAD_INPUT
    _core_log(source, logs)
    return _serve(args, plan, hub, source, ctx, annotator, logs)


def _core_output(args: argparse.Namespace, plan: Any, view: Any, timeout: float) -> Any:
    """How the compiled core writes the observation's lines
    (:class:`~mbmon.sources.proxy.CoreOutput`), or ``None`` when the options keep it
    off the core (``--debug-core`` says why)."""
    from mbmon.commands.common import err
    from mbmon.commands.screen import _interactive
    from mbmon.core.chunks import decline_for_proxy

    console = not args.quiet and (args.json or getattr(args, "plain", False) or not _interactive())
    why = decline_for_proxy(args, process=plan.process, console=console)
    buffer = None
    if why is None and console:
        from mbmon.sinks.console import utf8_buffer

        buffer = utf8_buffer(sys.stdout)
        if buffer is None:
            why = "stdout is not UTF-8"
    if getattr(args, "debug_core", False):
        err(
            "core: "
            + ("the compiled core observes the proxy" if why is None else f"declined ({why})")
        )
    from mbmon.sources.proxy import CoreOutput

    if why is None and args.quiet:
        return CoreOutput(view, args.json, timeout, None, None)
    if why is not None or buffer is None:
        return None
    from mbmon.sinks.console import RawStdout

    raw = RawStdout(buffer)
    return CoreOutput(view, args.json, timeout, raw.write, raw.flush)


def _core_log(source: Any, logs: list[Any]) -> None:
    """The core observing with a ``-w x.mcap`` log writes its messages itself (into
    the same sink, which the hub feeds after a hand-over); before the hub's loop runs."""
    if source.live is None or not logs:
        return
    from mbmon.sinks.mcap import McapSink

    (sink,) = logs  # decline_for_proxy: one log at most, a .mcap
    if not isinstance(sink, McapSink):  # pragma: no cover - declined before
        raise RuntimeError(f"the core cannot write {type(sink).__name__}")
    source.live.log_to(sink)


def _open_logs(args: argparse.Namespace, ctx: Any) -> list[Any] | None:
    """The Foxglove feed and the ``-w`` logs, opened (not attached: the command hands
    them to :func:`~mbmon.commands.listeners.attach_outputs`, logs first); ``None``
    (said on stderr) when one cannot be opened."""
    from mbmon.commands.common import err, open_foxglove, open_logs
    from mbmon.sinks.base import SinkError

    logs: list[Any] = []
    try:
        feed = open_foxglove(args, ctx)  # before any file: a missing SDK leaves nothing behind
        logs += [feed] if feed is not None else []
        logs += open_logs(args.write, ctx, args)  # closes its own on failure
    except (SinkError, SystemExit) as exc:
        for out in logs:
            out.close()
        if isinstance(exc, SystemExit):
            raise
        err(str(exc))
        return None
    return logs


def _serve(
    args: argparse.Namespace,
    plan: Any,
    hub: Any,
    source: Any,
    ctx: Any,
    annotator: Any,
    logs: list[Any],
) -> int:
    """The listening proxy's run: signals, the start-up line, the outputs (the opened
    ``logs``, then the screen), ``run_sources`` until Ctrl-C/SIGTERM, then the
    summary and the exit status."""
    from mbmon.commands.common import (
        Figures,
        attach_outputs,
        err,
        exit_status,
        open_console,
        run_live,
        stop_on_signals,
    )
    from mbmon.sources.base import run_sources

    from_screen = [0]  # the monitor's quit key asks as a signal does

    def stop(count: int) -> None:
        source.runner.stop()  # the engine's last events reach the hub, then it stops the hub
        if count > 1:
            hub.stop()  # asked twice: do not wait for the engine

    def quit_key() -> None:
        from_screen[0] += 1
        stop(signals.count + from_screen[0])

    # Ctrl-C and SIGTERM stop the engine from now on: before the start-up line, which
    # is what a supervisor (or a test) waits for before it may signal; and until the
    # summary is out (a late Ctrl-C must not cut the logs' close or the summary short)
    with stop_on_signals(stop) as signals:
        print(f"mbmon proxy: {plan.startup_line(source.address)}", file=sys.stderr, flush=True)
        if args.upstream is not None:
            _warn_unresolved(source, plan.config.upstream_host, plan.config.upstream_port)
        # the screen last: the logs are open, and the start-up line is on the terminal
        # before the live monitor takes it
        console, monitor = open_console(
            args, ctx.view, title=f"mbmon proxy -> {plan.upstream}", annotator=annotator
        )
        attach_outputs(hub, logs=logs, screen=console)
        if monitor is not None:
            hub.add_listener(Figures(monitor, source.stats))
        try:
            run_live(
                monitor, partial(run_sources, hub, [source]), quit_key, ctx=ctx, submit=hub.submit
            )
        finally:
            source.stop()
            hub.close()
        print("mbmon proxy: " + "\n  ".join(source.summary()), file=sys.stderr)
        lost = source.ended_unexpectedly
        if lost:
            status = getattr(source.runner, "returncode", None)
            err(
                f"the proxy's forwarding process ended unexpectedly (status {status}); "
                "the counters above are the last it sent"
            )
    return exit_status(hub, failed=lost, until_signal=True)


def _warn_unresolved(source: Any, host: str, port: int) -> None:
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
    source.put_event(Event(time.time(), None, EventKind.NOTICE, {"message": warning}))
