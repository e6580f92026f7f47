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
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Any

__all__ = ["DEFAULT_LOG", "GUARD_SPEC", "register", "run"]

#: The log the demo writes in the current directory unless ``-w`` says otherwise.
DEFAULT_LOG = "mbmon-demo.mcap"
#: The write the demo's guard refuses: the robot's system inputs SI1..SI256 (Table 12).
GUARD_SPEC = "coil:0-255"
#: ``source`` of a demo log's metadata; a log whose source starts so may be overwritten.
SOURCE_PREFIX = "mbmon demo"
#: Pauses (seconds) so that a human can follow the live screen: after each request
#: (not the polls of a running motion), and at the start of each part.
STEP_PAUSE = 0.12
PART_PAUSE = 0.9
#: The proxy's gateway timeout in the demo (the pipeline waits one second longer).
PROXY_TIMEOUT = 3.0

_MCAP_MAGIC = b"\x89MCAP0\r\n"

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


# --------------------------------------------------------------------------- the log file


def is_demo_log(path: Path) -> bool:
    """Whether ``path`` is an MCAP log an earlier ``mbmon demo`` wrote (so it may be overwritten).

    The file must start with the MCAP magic and a header written by mbmon, and
    its ``mbmon`` metadata must name the demo as its source.
    """
    try:
        with path.open("rb") as f:
            head = f.read(64)
    except OSError:
        return False
    if not head.startswith(_MCAP_MAGIC) or len(head) < 8 + 9 + 4:
        return False
    if head[8] != 0x01:  # the Header record
        return False
    pos = 8 + 9
    (n,) = struct.unpack_from("<I", head, pos)  # profile
    pos += 4 + n
    if pos + 4 > len(head):
        return False
    (n,) = struct.unpack_from("<I", head, pos)  # library
    if not head[pos + 4 : pos + 4 + n].startswith(b"mbmon"):
        return False
    from mbmon.io.mcap.layout import METADATA_NAME
    from mbmon.io.mcap.reader import LogError, McapLog

    try:
        with McapLog(path) as log:
            source = log.metadata.get(METADATA_NAME, {}).get("source", "")
    except (LogError, OSError, ValueError):
        return False
    return source.startswith(SOURCE_PREFIX)


def check_log_path(text: str) -> Path:
    """The ``-w`` path, or a :class:`UsageError` when it is not a .mcap name or would
    overwrite anything but an earlier demo's log."""
    from mbmon.commands.common import UsageError

    path = Path(text)
    if path.suffix.lower() != ".mcap":
        raise UsageError(
            f"{text}: the demo writes an MCAP log: use a name ending in .mcap "
            "(mbmon export converts it to .csv, .jsonl, .txt or .pcap afterwards)"
        )
    if path.is_dir():
        raise UsageError(f"{text}: is a directory")
    if path.exists() and not is_demo_log(path):
        raise UsageError(
            f"{text}: exists and is not the log of an earlier demo; refusing to overwrite "
            "it (choose another name with -w)"
        )
    return path


# --------------------------------------------------------------------------- the client


class _Stopped(Exception):
    """Ctrl-C or SIGTERM while the client runs."""


class DemoClient:
    """The client side of the demo: the program, the guarded write, the narration.

    Runs in its own thread (:meth:`run`). Narration goes into the hub as NOTICE
    events through ``say``; ``pause`` paces the steps. Results are kept for the
    closing summary: ``result`` (the program's), ``refused`` (the guard's answer
    code), ``error`` (why a step failed).
    """

    def __init__(
        self,
        host: str,
        port: int,
        say: Any,
        *,
        fast: bool,
        stop: threading.Event,
    ) -> None:
        self.host, self.port = host, port
        self.say = say
        self.fast = fast
        self.stop = stop
        self.result: Any = None
        self.refused: int | None = None
        self.ptp_status: int | None = None
        self.requests = 0
        self.finished: float | None = None  # time.monotonic() when the client was done
        self.error: str | None = None
        self._client: Any = None

    def pause(self, seconds: float) -> None:
        if self.stop.wait(0 if self.fast else seconds):
            raise _Stopped

    def on_part(self, part: str) -> None:
        """Before a part's first request: narrate it, give the eye time to read it."""
        text = _PARTS.get(part)
        if text is not None:
            self.say(text)
            self.pause(PART_PAUSE)

    def on_step(self, step: Any) -> None:
        """After each answered request: pace the step."""
        self.requests += 1
        polling = step.function == 4 and step.address == 524 and step.result == (2,)
        self.pause(0 if polling else STEP_PAUSE)
        if step.part == "5.4.5.2" and (step.function, step.address, step.values) == (16, 200, (1,)):
            self._ptp_status()

    def _ptp_status(self) -> None:
        """The one request the demo adds to §5.4.5.2: IR200 after the PTP's R200 = 1, so
        the PTP's outcome (accepted: 1 Success) is on the wire and in the log."""
        self.say(_PTP_STATUS)
        from mbmon.sim.program import ProgramError

        rr = self._client.read_input_registers(200, count=1, device_id=1)
        self.requests += 1
        if rr.isError():
            raise ProgramError(f"IR200 after the PTP: {rr}")
        self.ptp_status = int(rr.registers[0])
        self.pause(STEP_PAUSE)

    def run(self) -> None:
        from pymodbus.client import ModbusTcpClient

        from mbmon.sim.program import ProgramError, run_program

        client = ModbusTcpClient(self.host, port=self.port, timeout=PROXY_TIMEOUT + 1, retries=0)
        self._client = client
        try:
            if not client.connect():
                self.error = f"cannot connect to the proxy at {self.host}:{self.port}"
                return
            self.say(_INTRO)
            self.pause(PART_PAUSE)
            self.result = run_program(
                self.host,
                self.port,
                client=client,
                on_step=self.on_step,
                on_part=self.on_part,
                poll=0.1,
                timeout=20.0,
            )
            self.say(_GUARD)
            self.pause(PART_PAUSE)
            rr = client.write_coil(0, True, device_id=1)
            self.requests += 1
            self.refused = getattr(rr, "exception_code", None) if rr.isError() else 0
            self.pause(STEP_PAUSE)
            if self.refused != 1:
                self.error = f"the guarded write of SI1 was not refused (answer {rr})"
        except _Stopped:
            self.error = "interrupted"
        except ProgramError as exc:
            self.error = str(exc)
        except Exception as exc:  # pymodbus raises its own exceptions on a lost connection
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            client.close()
            self.finished = time.monotonic()


#: The narration, one NOTICE per part (short: a live screen row is about 100 characters).
_INTRO = (
    "demo §5.4.5.2: read speed IR100, R100 = 90 %, read DI[1..8], write DO[1..5], "
    "PTP {A1 90} via R200/R201.., poll IR524 until Idle"
)
_PTP_STATUS = "demo: one read the program leaves out: IR200, the PTP's status (1 Success, 2 Fail)"
_GUARD = (
    f"demo guard: the proxy refuses writes to SI1..SI256 ({GUARD_SPEC}); "
    "the client writes SI1 Start = ON"
)
_PARTS = {
    "LIN": "demo LIN {X -300, Y 300, Z 400, A 180, B 0, C 90} Vel=1000mm/s: R200 = 0, "
    "R201.., R200 = 1, IR200, IR524, X..C in IR400..IR411",
    "Set PR": "demo Set PR: $PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0} (command 100), IR200",
    "Get PR": "demo Get PR[2] (command 200): the robot returns PR[2] in IR202..IR215",
    "JOG": "demo JOG A1 +: moves while R200 stays 1; R200 = 0 stops it",
}


# --------------------------------------------------------------------------- run


def run(args: argparse.Namespace) -> int:
    """Start sim and proxy, run the client through the hub, print what to do next."""
    import signal

    from mbmon.commands.common import (
        EXIT_BAD_INPUT,
        EXIT_INTERRUPTED,
        EXIT_OK,
        err,
        make_annotator,
        open_console,
        open_foxglove,
        profile_sources,
        run_live,
    )
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.model import Event, EventKind
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.proxy.config import ProxyConfig, endpoint
    from mbmon.proxy.guard import Guard
    from mbmon.proxy.runner import attach_engine
    from mbmon.sim.server import SimServer
    from mbmon.sinks.base import SinkContext, SinkError, open_sink

    log_path = check_log_path(args.write)

    sim = SimServer(host="127.0.0.1", port=0, unit=1)
    try:
        sim.start()
    except OSError as exc:
        err(f"cannot start the simulated robot: {exc}")
        return EXIT_BAD_INPUT
    sim_host, sim_port = sim.host, sim.port
    robot = endpoint(sim_host, sim_port)
    guard = Guard.from_options(False, [], [GUARD_SPEC])
    config = ProxyConfig(
        upstream_host=sim_host,
        upstream_port=sim_port,
        listen_host="127.0.0.1",
        listen_port=0,
        timeout=PROXY_TIMEOUT,
        guard=guard,
    )
    view = View(robot=robot, robot_is_client=False)
    annotator = make_annotator(args.profile)
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
        hub.add_listener(open_sink(str(log_path), ctx))  # the log first: all is logged
    except SinkError as exc:
        about_log = str(exc).startswith(f"{log_path}:")
        err(f"{exc} (log elsewhere: mbmon demo -w DIR/{DEFAULT_LOG})" if about_log else str(exc))
        if feed is not None:
            feed.close()
        hub.close()
        sim.stop()
        return EXIT_BAD_INPUT
    except SystemExit:
        sim.stop()
        raise
    if feed is not None:
        hub.add_listener(feed)
    console, monitor = open_console(args, view, title="mbmon demo", annotator=annotator)
    if console is not None:
        hub.add_listener(console)
    engine, thread, observer = attach_engine(hub, config)
    try:
        proxy_host, proxy_port = thread.start()
    except OSError as exc:
        err(f"cannot start the proxy: {exc.strerror or exc}")
        hub.run(until_idle=True)
        hub.close()
        sim.stop()
        return EXIT_BAD_INPUT
    proxy = endpoint(proxy_host, proxy_port)
    if monitor is not None:
        monitor.set_figures({"robot (sim)": robot, "proxy": proxy})

    def say(message: str) -> None:
        hub.put(Event(time.time(), None, EventKind.NOTICE, {"message": message}))

    stop = threading.Event()
    signals = [0]
    keeping = threading.Event()  # set once the demo is done and the cell is left running

    def _stop(signum: int, frame: object) -> None:
        signals[0] += 1
        stop.set()
        thread.stop()  # the engine's last events reach the hub, then it stops the hub
        if signals[0] > 1:
            hub.stop()

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
    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    started = time.monotonic()
    try:
        try:
            worker.start()
            run_live(
                monitor,
                hub.run,
                lambda: _stop(signal.SIGINT, None),
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
            sim.stop()
            hub.close()
        engine.stats.not_observed = observer.skipped
    finally:  # a late Ctrl-C must not cut the log's close short
        for s, handler in old.items():
            signal.signal(s, handler)
    elapsed = (client.finished or time.monotonic()) - started  # not the --keep-running time
    failed_outputs = [f"{name}: {why}" for name, why in hub.failures if name != "stdout"]
    if failed_outputs:
        for line in failed_outputs:
            err(line)
        return EXIT_BAD_INPUT
    if client.error == "interrupted" or (signals[0] and not keeping.is_set()):
        err(f"demo interrupted; what was recorded is in {log_path}")
        return EXIT_INTERRUPTED
    if client.error is not None:
        err(f"demo failed: {client.error}; what was recorded is in {log_path}")
        return EXIT_BAD_INPUT
    _closing(log_path, client, elapsed, quiet=args.quiet)
    return EXIT_OK


def _wait_until(done: Any, timeout: float) -> bool:
    """Poll ``done()`` every 10 ms for up to ``timeout`` seconds; whether it came true."""
    deadline = time.monotonic() + timeout
    while not done():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _closing(log: Path, client: DemoClient, elapsed: float, *, quiet: bool) -> None:
    """What the demo did and how to look at the log again (stdout, after the live screen)."""
    result = client.result
    status = result.statuses
    name = str(log)
    if any(c.isspace() for c in name):
        name = repr(name)
    lines = [
        "",
        f"mbmon demo: done in {elapsed:.1f} s, {client.requests} requests through the proxy",
        f"  PTP {{A1 90}}: status {client.ptp_status}, A1 = {result.joints[0]:g}°; "
        f"LIN status {status.get('LIN')}, X Y Z = {' '.join(f'{v:g}' for v in result.pose[:3])}",
        f"  Set PR {status.get('Set PR')}, Get PR {status.get('Get PR')} (1 = success); "
        f"JOG moved A1 {result.jog_moved:.2f}° ({result.jog_from:g} → {result.jog_to:g}°)",
        f"  the write of SI1 Start was refused by the guard (exception {client.refused:02X})",
        f"  log: {name}",
        "",
        "next:",
        f"  mbmon replay {name}                 the run again, as it was shown",
        f"  mbmon replay {name} --grep Guard    the refused write in the audit",
        f"  mbmon info {name}                   what the log holds",
        f"  mbmon replay {name} --serve         the recorded robot on 127.0.0.1:1502, for a client",
        f"  Foxglove: open {name} in https://app.foxglove.dev (or Foxglove desktop):",
        "    Log panel on /modbus/monitor, Plot on /hrss/state.a1, Raw Messages on /hrss/commands",
    ]
    if not quiet:
        print("\n".join(lines), flush=True)
