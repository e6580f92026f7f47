"""The argparse option groups every command shares (the value types they use are
:mod:`mbmon.commands.values`'s, re-exported here).

Re-exported by :mod:`mbmon.commands.common`. A bad value is an
``argparse.ArgumentTypeError`` (argparse prints it with the usage, exit 2), or a
:class:`~mbmon.commands.ending.UsageError` for values checked after parsing.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from mbmon.commands.values import (  # the value types the option groups use
    endpoint,
    port,
    positive,
    positive_int,
)

# --------------------------------------------------------------------------- option groups


def add_view_options(parser: argparse.ArgumentParser) -> None:
    """Options that decide how records are labelled and annotated (every observing command)."""
    group = parser.add_argument_group("labels and meaning")
    group.add_argument(
        "--robot",
        metavar="HOST[:PORT]",
        type=endpoint,
        help="the robot's endpoint: print the robot's own Modbus Monitor labels "
        '("Receive from client", "Send to server", ...); for RTU give the bus name',
    )
    group.add_argument(
        "--robot-client",
        action="store_true",
        help="on an RTU bus, the robot named by --robot is the master (client)",
    )
    group.add_argument(
        "--profile",
        action="append",
        default=[],
        metavar="SPEC",
        help="device profile for annotations: NAME or FILE.toml for all servers, "
        "HOST[:PORT]=NAME or unit:N=NAME for one (repeatable; built-in: hrss, xeg)",
    )


def add_port_options(group: Any) -> None:
    """``--port`` and ``--rtu-port``: which TCP/UDP ports carry Modbus (``read``, ``sniff``)."""
    group.add_argument(
        "--port",
        action="append",
        type=port,
        default=[],
        metavar="N",
        help="Modbus/TCP (and Modbus/UDP) server port, besides 502 (repeatable)",
    )
    group.add_argument(
        "--rtu-port",
        action="append",
        type=port,
        default=[],
        metavar="N",
        help="TCP/UDP port carrying RTU ADUs with CRC, as some gateways do (repeatable)",
    )
    group.add_argument(
        "--no-detect",
        action="store_true",
        help="do not look for Modbus/TCP and RTU over TCP on other TCP ports (by default "
        "a connection on any port whose bytes are Modbus, a request and its answer, "
        "becomes a stream; docs/usage.md)",
    )


def add_output_options(parser: argparse.ArgumentParser) -> None:
    """``--json``, ``-w FILE``, ``-q``: where records go (every observing command)."""
    group = parser.add_argument_group("output")
    group.add_argument(
        "--json", action="store_true", help="one JSON object per line (docs/json.md)"
    )
    group.add_argument(
        "-w",
        "--write",
        action="append",
        default=[],
        metavar="FILE",
        help="also write records to FILE; format by suffix: .mcap .jsonl .csv .txt .pcap "
        ".parquet (repeatable; .parquet needs pip install 'mbmon[parquet]')",
    )
    group.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="print no records and no summary (use with -w)",
    )
    group.add_argument(
        "--rotate",
        action="append",
        default=[],
        metavar="TIME|SIZE",
        help="-w files rotate: a new file every TIME of capture time (1h, 30min, 1d; "
        "aligned to whole periods) and/or once a file holds SIZE (100MB, 1GiB); each file "
        "is finished on its own and named FILE_NNNNN_<start time>Z.SUFFIX",
    )
    group.add_argument(
        "--keep",
        type=positive_int,
        metavar="N",
        help="with --rotate or --trigger: keep the newest N files of each -w ring, remove "
        "older ones",
    )
    group.add_argument(
        "--trigger",
        metavar="EXPR",
        help="keep (log and show) only windows around the records EXPR matches, e.g. "
        "'exception or timeout', 'fc 6 and address 200', 'R200 != 0', 'latency > 50ms'; "
        "each window is a -w file of its own (the grammar of --where; docs/usage.md)",
    )
    group.add_argument(
        "--before",
        default="30s",
        metavar="TIME",
        help="with --trigger: keep TIME before each trigger (default 30s)",
    )
    group.add_argument(
        "--after",
        default="10s",
        metavar="TIME",
        help="with --trigger: keep TIME after each trigger (default 10s; a trigger within "
        "a window extends it)",
    )


def add_live_options(group: Any) -> None:
    """``--plain``: the choice between the monitor screen and plain lines (live commands)."""
    group.add_argument(
        "--plain",
        action="store_true",
        help="one line per record instead of the interactive monitor (the default when "
        "stdout or stdin is not a terminal)",
    )


def add_serial_line_options(
    group: Any, *, baud_default: int | None, bytesize: bool = False, prefix: str = ""
) -> None:
    """``--baud``, ``--parity``, ``--stopbits`` (and ``--bytesize``): the serial line's
    settings, the one home of their spelling and defaults (``sniff``, ``proxy``,
    ``sim``). ``baud_default`` ``None`` leaves ``--baud`` unset when not given (the
    command applies :data:`~mbmon.sources.DEFAULT_BAUD` and can tell "not given");
    ``prefix`` starts the helps (``"RTU "``)."""
    from mbmon.sources import DEFAULT_BAUD

    group.add_argument(
        "--baud",
        type=positive_int,
        default=baud_default,
        metavar="N",
        help=f"{prefix}baud rate ({DEFAULT_BAUD})",
    )
    group.add_argument("--parity", choices=("N", "E", "O"), default="N", help=f"{prefix}parity (N)")
    group.add_argument(
        "--stopbits", type=int, choices=(1, 2), default=1, help=f"{prefix}stop bits (1)"
    )
    if bytesize:
        group.add_argument(
            "--bytesize", type=int, choices=(5, 6, 7, 8), default=8, help=f"{prefix}data bits (8)"
        )


def add_interface_options(parser: argparse.ArgumentParser) -> None:
    """The ``network`` group of ``sniff``: ``-i IFACE``, ``--list``, ``-f BPF`` and the
    Modbus ports (:func:`add_port_options`)."""
    group = parser.add_argument_group("network")
    group.add_argument("-i", "--interface", dest="interface", metavar="IFACE", help="as IFACE")
    group.add_argument("--list", action="store_true", help="list the network interfaces and exit")
    group.add_argument(
        "-f",
        "--filter",
        metavar="BPF",
        help="kernel capture filter (tcpdump syntax) instead of the default: 'tcp or "
        "udp port 502' while Modbus is looked for on every TCP port (no --port, "
        "--rtu-port or --no-detect), else 'tcp port 502 or udp port 502' plus those ports",
    )
    add_port_options(group)


def add_serial_tap_options(parser: argparse.ArgumentParser) -> None:
    """The ``serial`` group of ``sniff``: one or two ``--serial`` taps, the line's
    settings (:func:`add_serial_line_options`, ``--baud`` unset when not given) and
    the two taps' ``--merge-window``."""
    group = parser.add_argument_group("serial (RS485, Modbus RTU)")
    group.add_argument(
        "--serial",
        action="append",
        default=[],
        metavar="PORT",
        help="serial port of a passive RS485 tap; give it twice for two one-direction "
        "taps merged by timestamp",
    )
    add_serial_line_options(group, baud_default=None, bytesize=True)
    group.add_argument(
        "--merge-window",
        type=positive,
        default=0.05,
        metavar="S",
        help="with two taps: hold reads S seconds to merge them in time order (0.05)",
    )


def add_capture_run_options(
    parser: argparse.ArgumentParser, add_count: Callable[[Any], None]
) -> Any:
    """The ``run`` group of a live capture (``sniff``): ``-c N`` (``add_count``: the one
    ``-c``, :func:`~mbmon.commands.listeners.add_count_option`, handed in because
    the listeners import this module), ``--timeout S`` and ``--plain``. Returns the
    group, for the command's own options."""
    group = parser.add_argument_group("run")
    add_count(group)
    group.add_argument(
        "--timeout",
        type=positive,
        default=1.0,
        metavar="S",
        help="report a request unanswered after S seconds (default 1.0)",
    )
    add_live_options(group)
    return group
