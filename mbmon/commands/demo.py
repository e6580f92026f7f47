"""``mbmon demo``: a whole robot cell on loopback, watched live, in under 30 seconds.

Wiring only, around the one flow. It starts the simulated HRSS controller
(:class:`~mbmon.sim.server.SimServer`, "the robot") on a free loopback port and
the proxy engine in front of it (:func:`mbmon.proxy.runner.attach_engine`, the
same wiring as ``mbmon proxy``) with a write guard that refuses writes to the
robot's system inputs SI1..SI256 (coils 0-255). A client thread runs the
manual's §5.4.5.2 program plus LIN, Set/Get PR and JOG
(:func:`mbmon.sim.program.run_program`) and then one write the guard refuses,
all through the proxy. What passes goes, like every source, into one
:class:`~mbmon.hub.Hub`: HRSS profile, the robot's labels, the live monitor or
plain lines (:func:`mbmon.commands.common.open_console`) and an MCAP log. The
demo's own narration (what each part of the program does) goes into the hub as
NOTICE events, so it is on the screen and in the log in the traffic's order.

Threads: the main thread runs ``hub.run``; the sim and the proxy each run their
own asyncio loop; the client runs in a worker thread and, unless
``--keep-running``, stops the proxy when it is done (the proxy's thread then
stops the hub). Ctrl-C or SIGTERM stop the client, the proxy and the sim; the
log is always closed.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any

from mbmon.commands.demo_client import GUARD_SPEC, PROXY_TIMEOUT, DemoClient, closing
from mbmon.commands.demo_log import SOURCE_PREFIX, check_log_path, is_demo_log

__all__ = ["DEFAULT_LOG", "GUARD_SPEC", "is_demo_log", "register", "run"]

#: The log the demo writes in the current directory unless ``-w`` says otherwise.
DEFAULT_LOG = "mbmon-demo.mcap"

_DESCRIPTION = """\
A robot cell on this machine, in under 30 seconds, with nothing to configure and
nothing beyond loopback (127.0.0.1), no root:

  client program ──▶ mbmon proxy (127.0.0.1:free port) ──▶ mbmon sim (127.0.0.1:free port)
  (§5.4.5.2 of the     forwards, shows, logs, and           a simulated HRSS controller:
   HIWIN manual)       refuses writes to SI1..SI256         the "robot" (a test partner,
                                                            not a robot simulator)

The client is the program of the HIWIN manual's §5.4.5.2 (one robot driving
another over Modbus/TCP): read the speed (IR100), set it to 90 % (R100), read
DI[1..8], write DO[1..5], PTP {A1 90} Vel=50% Acc=100% TOOL[1] BASE[2] through
the R200/R201.. command handshake, and poll IR524 until the motion is idle. Then
LIN, Set PR[2], Get PR[2], JOG A1+, and a write of SI1 Start that the proxy's
guard refuses (exception 01, audited as a GUARD event).

You watch it as the robot's Modbus Monitor would show it (the robot = the sim),
with HRSS notes, the reconstructed commands and their outcome, and the robot's
state (A1..A6, X..C). Everything is logged to mbmon-demo.mcap; at the end the
demo prints how to replay it, summarise it and open it in Foxglove."""

_EPILOG = f"""\
examples:
  mbmon demo                      the live screen, log in ./{DEFAULT_LOG}
  mbmon demo --plain              plain monitor lines (automatic when stdout is not a terminal)
  mbmon demo -w first.mcap        log somewhere else
  mbmon demo --keep-running       afterwards, leave the sim and the proxy up for your own
                                  client (their addresses are printed); Ctrl-C ends it
  mbmon demo --fast               no pauses between steps (tests, CI)
  mbmon demo --foxglove --keep-running   watch it live in Foxglove (ws://127.0.0.1:8765;
                                  needs pip install 'mbmon[foxglove]')

afterwards:
  mbmon replay {DEFAULT_LOG}                     the run again, line by line
  mbmon replay {DEFAULT_LOG} --fc 16 --grep R200 only the command writes
  mbmon info {DEFAULT_LOG}                       span, streams, function codes, commands
  open {DEFAULT_LOG} in Foxglove (https://app.foxglove.dev): Log panel on /modbus/monitor,
  Plot panel on /hrss/state (A1..A6), Raw Messages on /hrss/commands

the log: -w must name a .mcap file. An existing file is overwritten only when it
is the log of an earlier demo; anything else (another mbmon log, any other file)
is refused, so a demo never destroys a capture or log of yours.
exit status: 0 ok (also after Ctrl-C with --keep-running), 1 a step failed or the
log cannot be written, 2 usage, 130 interrupted during the demo
See docs/demo.md."""


def register(sub: Any) -> None:
    """Add the ``demo`` subparser to ``sub``."""
    from mbmon.commands.common import add_foxglove_option, add_live_options

    p = sub.add_parser(
        "demo",
        help="a simulated robot, a proxy and a client program on loopback, watched live "
        "(start here)",
        description=_DESCRIPTION,
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "-w",
        "--write",
        default=DEFAULT_LOG,
        metavar="FILE",
        help=f"the MCAP log to write (default ./{DEFAULT_LOG}); an existing file is "
        "overwritten only if it is an earlier demo's log",
    )
    add_live_options(p)
    p.add_argument(
        "--keep-running",
        action="store_true",
        help="after the program, keep the sim and the proxy running for your own Modbus "
        "client (addresses printed) until Ctrl-C; the log records your traffic too",
    )
    p.add_argument(
        "--fast",
        action="store_true",
        help="no pauses between the steps (for tests and CI; too fast to follow by eye)",
    )
    add_foxglove_option(p)
    p.set_defaults(func=run, quiet=False, json=False, profile=["hrss"])


# --------------------------------------------------------------------------- run


def run(args: argparse.Namespace) -> int:
    """Start sim and proxy, run the client through the hub, print what to do next."""
    from mbmon.commands.common import EXIT_BAD_INPUT, err, make_annotator
    from mbmon.format import View
    from mbmon.proxy.config import endpoint
    from mbmon.sim.server import SimServer

    log_path = check_log_path(args.write)
    sim = SimServer(host="127.0.0.1", port=0, unit=1)
    try:
        sim.start()
    except OSError as exc:
        err(f"cannot start the simulated robot: {exc}")
        return EXIT_BAD_INPUT
    try:
        robot = endpoint(sim.host, sim.port)
        view = View(robot=robot, robot_is_client=False)
        return _run_cell(args, log_path, sim, view, make_annotator(args.profile))
    finally:
        sim.stop()


def _run_cell(args: argparse.Namespace, log_path: Path, sim: Any, view: Any, annotator: Any) -> int:
    """The proxy in front of the running ``sim``, the hub with its outputs (the log,
    then Foxglove, then the screen), the client; then the one exit status."""
    from mbmon.commands.common import (
        EXIT_BAD_INPUT,
        attach_outputs,
        err,
        exit_status,
        open_console,
        open_foxglove,
        output_failed,
        profile_sources,
        run_live,
        stop_on_signals,
    )
    from mbmon.hub import Hub
    from mbmon.model import Event, EventKind
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.proxy.config import ProxyConfig, endpoint
    from mbmon.proxy.guard import Guard
    from mbmon.proxy.runner import attach_engine
    from mbmon.sinks.base import SinkContext, SinkError, open_sink

    robot = view.robot
    guard = Guard.from_options(False, [], [GUARD_SPEC])
    pipe_timeout = PROXY_TIMEOUT + 1.0  # the proxy answers 0x0B itself at its timeout
    hub = Hub(Pipeline(annotator, PipelineConfig(timeout=pipe_timeout)))
    ctx = SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=f"{SOURCE_PREFIX}: client -> proxy (guard {guard.describe()}) -> sim {robot}",
        profiles=profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=pipe_timeout,
    )
    feed = None
    try:
        feed = open_foxglove(args, ctx)  # before any file: a missing SDK leaves nothing behind
        log = open_sink(str(log_path), ctx)
    except SinkError as exc:
        about_log = str(exc).startswith(f"{log_path}:")
        err(f"{exc} (log elsewhere: mbmon demo -w DIR/{DEFAULT_LOG})" if about_log else str(exc))
        if feed is not None:
            feed.close()
        return EXIT_BAD_INPUT
    console, monitor = open_console(args, view, title="mbmon demo", annotator=annotator)
    attach_outputs(hub, logs=[log, feed], screen=console)  # the log first: all is logged
    config = ProxyConfig(
        upstream_host=sim.host,
        upstream_port=sim.port,
        listen_host="127.0.0.1",
        listen_port=0,
        timeout=PROXY_TIMEOUT,
        guard=guard,
    )
    engine, thread, observer = attach_engine(hub, config)
    try:
        proxy_host, proxy_port = thread.start()
    except OSError as exc:
        err(f"cannot start the proxy: {exc.strerror or exc}")
        hub.run(until_idle=True)
        hub.close()
        return EXIT_BAD_INPUT
    proxy = endpoint(proxy_host, proxy_port)
    if monitor is not None:
        monitor.set_figures({"robot (sim)": robot, "proxy": proxy})

    def say(message: str) -> None:
        hub.put(Event(time.time(), None, EventKind.NOTICE, {"message": message}))

    stop = threading.Event()
    stops = [0]  # Ctrl-C, SIGTERM or the screen's quit
    keeping = threading.Event()  # set once the demo is done and the cell is left running

    def _stop(_count: int = 1) -> None:
        stops[0] += 1
        stop.set()
        thread.stop()  # the engine's last events reach the hub, then it stops the hub
        if stops[0] > 1:
            hub.stop()  # asked twice: do not wait for the engine

    client = DemoClient(proxy_host, proxy_port, say, fast=args.fast, stop=stop)

    def client_main() -> None:
        try:
            client.run()
        finally:
            if client.error is None and args.keep_running and not stop.is_set():
                keeping.set()
                say(f"demo done; until Ctrl-C: proxy {proxy} -> robot (sim) {robot}")
                if monitor is None:  # the live screen shows them in its header
                    print(
                        f"mbmon demo: keep running: proxy {proxy} -> robot (sim) {robot}; "
                        "Ctrl-C stops",
                        file=sys.stderr,
                        flush=True,
                    )
            else:
                _wait_until(lambda: not engine.clients, 2.0)  # its disconnect is observed
                thread.stop()

    worker = threading.Thread(target=client_main, name="mbmon-demo-client", daemon=True)
    started = time.monotonic()
    with stop_on_signals(_stop):  # a late Ctrl-C must not cut the log's close short
        try:
            worker.start()
            run_live(
                monitor,
                hub.run,
                _stop,
                ctx=ctx,
                submit=hub.submit,
                after=hub.close,  # the log is finished as the demo ends; the screen stays
                ended_note="demo done; q closes the screen, the summary follows",
            )
        finally:
            stop.set()
            thread.stop()
            thread.join(5.0)
            worker.join(5.0)
            hub.close()
        engine.stats.not_observed = observer.skipped
    elapsed = (client.finished or time.monotonic()) - started  # not the --keep-running time
    for name, why in hub.failures:
        if why != "broken pipe":
            err(f"{name}: {why}")
    interrupted = client.error == "interrupted" or (stops[0] > 0 and not keeping.is_set())
    status = exit_status(
        hub,
        interrupted=interrupted,
        failed=client.error is not None,
        until_signal=keeping.is_set(),  # --keep-running: Ctrl-C is how it ends
    )
    if output_failed(hub):
        pass  # said above, output by output
    elif status >= 128:
        err(f"demo interrupted; what was recorded is in {log_path}")
    elif client.error is not None:
        err(f"demo failed: {client.error}; what was recorded is in {log_path}")
    else:
        closing(log_path, client, elapsed, quiet=args.quiet)
    return status


def _wait_until(done: Any, timeout: float) -> bool:
    """Poll ``done()`` every 10 ms for up to ``timeout`` seconds; whether it came true."""
    deadline = time.monotonic() + timeout
    while not done():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True
