"""``mbmon sim``: serve a simulated HRSS robot controller over Modbus/TCP or RTU.

Owns the command line of the simulator and the console lines it prints; the
robot is :class:`mbmon.sim.robot.SimRobot`, the server :class:`mbmon.sim.server.SimServer`.
"""

from __future__ import annotations

import argparse
import sys
from typing import TextIO

__all__ = ["register", "run"]

DEFAULT_LISTEN = "127.0.0.1:1502"

_DESCRIPTION = """\
Serve a simulated HIWIN HRSS controller as a Modbus server: the register map of
the manual's chapter 5.3.3 (SI/DO coils, SO/DI discrete inputs, input and holding
registers) and the command protocol of Tables 16-43 (parameters in R201..R251,
R200 = 1 executes, status in IR200). Motions move the simulated joints or
Cartesian position over time; JOG and GO HOME run while R200 stays 1.

This is a test partner and a teaching tool, NOT a robot simulator: there is no
kinematics, no dynamics, no collision model and no robot program. Joint targets
move A1..A6, Cartesian targets move X..C, independently. Use it to try a PLC or
client program, a proxy or the monitor without a robot. See docs/sim.md."""

_EPILOG = """\
examples:
  mbmon sim                                 Modbus/TCP on 127.0.0.1:1502, unit 1
  mbmon sim --listen 127.0.0.1:5020 --unit 2
  mbmon sim --serial /dev/ttyUSB0 --baud 115200 --parity E
      Modbus RTU on a serial port (try a pty pair: socat -d -d pty,raw,echo=0 pty,raw,echo=0)
  mbmon sim --listen 0.0.0.0:502            every interface (only when you mean it)

then, from another terminal, any Modbus client (A1..A6 are IR300..IR311), or the
manual's 5.4.5.2 client program (PTP {A1 90}, then LIN, Set/Get PR, JOG):
  python -c "from mbmon.sim import run_program; run_program('127.0.0.1', 1502, on_step=print)"

exit status: 0 stopped by Ctrl-C or SIGTERM, 1 cannot listen or open the port, 2 usage
"""


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add the ``sim`` subparser."""
    from mbmon.commands.common import add_serial_line_options, listen_address, unit_id
    from mbmon.sources import DEFAULT_BAUD

    p = sub.add_parser(
        "sim",
        help="serve a simulated HRSS robot (a test partner, not a robot simulator)",
        description=_DESCRIPTION,
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--listen",
        metavar="HOST:PORT",
        type=listen_address,
        default=listen_address(DEFAULT_LISTEN),
        help=f"Modbus/TCP address to listen on (default {DEFAULT_LISTEN}; port 0 picks a free one)",
    )
    p.add_argument("--unit", type=unit_id, default=1, help="unit id the robot answers (default 1)")
    p.add_argument("--serial", metavar="PORT", help="serve Modbus RTU on this serial port instead")
    add_serial_line_options(p, baud_default=DEFAULT_BAUD, prefix="RTU ")  # as sniff and proxy
    p.add_argument(
        "-q", "--quiet", action="store_true", help="do not print executed commands and motions"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C or SIGTERM; print the address, then one line per command and motion."""
    import asyncio
    import logging
    import time

    from mbmon.commands.common import EXIT_BAD_INPUT, exit_status, loop_stops_on_signals
    from mbmon.sim.robot import SimEvent
    from mbmon.sim.server import SimServer

    out: TextIO = sys.stdout
    start = time.monotonic()

    def show(ev: SimEvent) -> None:
        if args.quiet:
            return
        mark = "" if ev.ok else " !"
        print(f"{ev.ts - start:9.3f}  {ev.kind:<14}{mark} {ev.text}", file=out, flush=True)

    host, port = args.listen
    server = SimServer(
        host=host,
        port=port,
        unit=args.unit,
        serial=args.serial,
        baudrate=args.baud,
        parity=args.parity,
        stopbits=args.stopbits,
        on_event=show,
    )

    def ready() -> None:
        if args.serial:
            where = f"Modbus RTU on {args.serial} ({args.baud} baud, 8{args.parity}{args.stopbits})"
        else:
            where = f"Modbus/TCP on {server.host}:{server.port}"
        print(f"mbmon sim: HRSS robot, unit {args.unit}, {where}", file=out)
        print(
            "mbmon sim: a test partner and teaching tool, not a robot simulator; Ctrl-C stops",
            file=out,
            flush=True,
        )
        if not args.serial and host not in ("127.0.0.1", "localhost", "::1"):
            print(f"mbmon sim: warning: listening on {host}, not loopback", file=sys.stderr)

    async def main() -> None:
        stop = asyncio.Event()
        with loop_stops_on_signals(asyncio.get_running_loop(), lambda _n: stop.set()):
            await server.serve(stop, ready)

    # pymodbus logs through the "pymodbus" logger; without a handler Python's last-resort
    # handler would print its warnings (a failed open) next to our own message
    logging.getLogger("pymodbus").addHandler(logging.NullHandler())
    try:
        asyncio.run(main())
    except OSError as exc:
        from mbmon.commands.common import listen_error, serial_open_error

        if args.serial:
            text = serial_open_error(args.serial, exc)
        else:
            text = listen_error(server.address, exc, port)
        print(f"mbmon sim: {text}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print("mbmon sim: stopped", file=out, flush=True)
    return exit_status(until_signal=True)  # Ctrl-C or SIGTERM is how it ends: 0
