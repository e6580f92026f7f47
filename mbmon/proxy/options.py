"""The options of ``mbmon proxy`` that are the proxy's own (network, serial sides,
guard) and its help's closing text; the command (:mod:`mbmon.commands.proxy`) adds
them to its parser with the command line's one set of value checks (``convert``),
and :class:`~mbmon.proxy.plan.ProxyPlan` reads them back."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["EPILOG", "add_proxy_options"]

EPILOG = """\
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
(MBMON_EVENT_LOOP=asyncio: asyncio's own loop) and observes at idle CPU priority
(MBMON_OBSERVE_PRIORITY=normal: at the priority it started with); TCP keepalive
finds vanished peers.
exit status: 0 ok, 1 cannot listen or an output failed, 2 usage
"""


def add_proxy_options(p: Any, convert: Mapping[str, Callable[..., Any]]) -> None:
    """Add the network, serial and guard option groups to the parser ``p``. ``convert``
    holds the command line's value checks by name, ``positive`` (seconds) and
    ``exception_code``, and ``serial_line``, which adds the serial line's ``--baud
    --parity --stopbits`` to a group (the commands' one builder)."""
    _positive = convert["positive"]
    exception_code = convert["exception_code"]
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
    convert["serial_line"](ser)  # --baud --parity --stopbits: the commands' one builder
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
