"""``mbmon replay LOG --serve`` and ``--to``: replay against servers (options and wiring).

:func:`add_options` adds the option group to the ``replay`` parser and
:func:`run` runs either mode; :mod:`mbmon.commands.replay` calls :func:`run` when
:func:`wanted` says one was asked for. The work itself lives in
:mod:`mbmon.io.exchanges` (the log as requests and answers),
:mod:`mbmon.io.emulate` (the register image and the emulating server) and
:mod:`mbmon.io.resend` (re-sending and comparing).

Exit status: ``--serve`` 0 when stopped by Ctrl-C or SIGTERM, 1 unreadable log
or cannot listen; ``--to`` 0 every live answer as recorded,
:data:`EXIT_DIFFERENT` (3) some answers differ, 1 unreadable log or the server
cannot be reached; 2 usage for both.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

from mbmon.commands.common import (
    EXIT_BAD_INPUT,
    EXIT_OK,
    EXIT_USAGE,
    UsageError,
    err,
    exception_code,
    exit_status,
    loop_stops_on_signals,
    positive,
)

#: ``replay --to``: the server answered, but not as recorded
EXIT_DIFFERENT = 3
DEFAULT_SERVE = "127.0.0.1:1502"

EPILOG = """\
against servers (debugging without the robot):
  mbmon replay cell.mcap --serve              emulate the recorded server on 127.0.0.1:1502
  mbmon replay cell.mcap --serve 127.0.0.1:0  on a free port (printed)
  mbmon replay cell.mcap --to 127.0.0.1:1502  re-send the recorded reads, diff the answers
  mbmon replay cell.mcap --to robot:502 --speed 1   at the original pace

--serve answers from the registers and coils the log shows: a read the log holds
gets the recorded answers in the recorded order (so a PLC polling IR524 sees the
motion run and end as recorded; --state first/last for a fixed image), takes
writes, answers what the log cannot with exception 02 (--miss-exception N) and
lists those requests at the end.
--to sends reads only: --writes also sends the recorded writes, which CAN MOVE A
ROBOT. Exit status of --to: 0 every answer as recorded, 3 some differ, 1 the log
cannot be read or the server cannot be reached, 2 usage.
"""


def add_options(parser: argparse.ArgumentParser) -> None:
    """The ``against servers`` option group of ``replay``."""
    group = parser.add_argument_group(
        "against servers",
        "emulate the recorded server (--serve) or re-send the recorded requests to a live "
        "one (--to) instead of printing the log",
    )
    group.add_argument(
        "--serve",
        nargs="?",
        const=DEFAULT_SERVE,
        metavar="ADDR:PORT",
        help=f"serve Modbus/TCP as the recorded server did (default {DEFAULT_SERVE}; "
        "port 0 picks a free one); Ctrl-C ends it and lists the requests it could not answer",
    )
    group.add_argument(
        "--miss-exception",
        type=exception_code,
        metavar="N",
        help="with --serve: the exception code for requests the log cannot answer (default 2, "
        "Illegal Data Address)",
    )
    group.add_argument(
        "--state",
        choices=("follow", "first", "last"),
        help="with --serve: follow (default): a read the log holds gets the recorded answers "
        "in their order, one per repetition (IR524 Running ... then Idle, as recorded), other "
        "requests the first values the log shows; first: every address holds its first value "
        "(the server as the recording found it); last: its last (as the recording left it)",
    )
    group.add_argument(
        "--to",
        metavar="HOST:PORT",
        help="re-send the recorded requests to this live Modbus/TCP server and print where "
        "its answers differ from the recorded ones (reads only, see --writes)",
    )
    group.add_argument(
        "--writes",
        action="store_true",
        help="with --to: also send the recorded writes (05 06 0F 10 15 16 17, and "
        "diagnostics that restart or clear). WRITES CAN MOVE A ROBOT: use only when nobody "
        "is in the cell",
    )
    group.add_argument(
        "--answer-timeout",
        type=positive,
        metavar="S",
        help="with --to: seconds to wait for each live answer (default 3)",
    )


def wanted(args: argparse.Namespace) -> bool:
    """Whether the command line asks for ``--serve`` or ``--to``."""
    return args.serve is not None or args.to is not None


def _check(args: argparse.Namespace) -> None:
    """Usage errors: options of the other modes, or of no mode."""
    if args.serve is not None and args.to is not None:
        raise UsageError("--serve and --to exclude each other")
    mode = "--serve" if args.serve is not None else "--to"
    for flag, given in (
        ("--json", args.json),
        ("--redecode", args.redecode),
        ("--robot", args.robot),
        ("--robot-client", args.robot_client),
        ("--grep", args.grep),
    ):
        if given:
            raise UsageError(f"{flag} does not apply to {mode}")
    if args.serve is not None:
        for flag, given in (
            ("--speed", args.speed),
            ("--writes", args.writes),
            ("--answer-timeout", args.answer_timeout),
        ):
            if given:
                raise UsageError(f"{flag} applies to --to, not --serve")
    else:
        for flag, given in (("--miss-exception", args.miss_exception), ("--state", args.state)):
            if given is not None:
                raise UsageError(f"{flag} applies to --serve, not --to")


def check_without_mode(args: argparse.Namespace) -> None:
    """Usage error for an option of this group given without ``--serve``/``--to``."""
    for flag, given in (
        ("--miss-exception", args.miss_exception),
        ("--state", args.state),
        ("--writes", args.writes or None),
        ("--answer-timeout", args.answer_timeout),
    ):
        if given is not None:
            raise UsageError(f"{flag} needs --serve or --to")


def run(
    args: argparse.Namespace,
    open_log: Callable[[str, str], tuple[Any, int]],
    log_times: Callable[[argparse.Namespace, Any], tuple[Any, Any]],
) -> int:
    """``replay --serve`` or ``--to``; ``open_log``/``log_times`` are replay's own
    (the log opened with its error messages, the time format and filters)."""
    from mbmon.commands.common import parse_address
    from mbmon.filters import FilterError

    try:
        _check(args)
        if args.serve is not None:  # proxy's --listen rule: loopback by default, port 0 ok
            host, port = parse_address(args.serve, "--serve", default_host="127.0.0.1", lowest=0)
        else:
            host, port = parse_address(args.to, "--to")
    except UsageError as exc:
        err(f"error: {exc}")
        return EXIT_USAGE
    log, status = open_log(args.log, "replay")
    if log is None:
        return int(status)
    with log:
        try:
            _fmt, flt = log_times(args, log)
        except FilterError as exc:
            err(f"error: {exc}")
            return EXIT_USAGE
        keep = flt.matches_record if flt.active else None
        if args.serve is not None:
            return _serve(args, log, keep, host, port)
        return _resend(args, log, keep, host, port)


def _serve(args: argparse.Namespace, log: Any, keep: Any, host: str, port: int) -> int:
    import asyncio

    from mbmon.io.emulate import TABLE_NAMES, EmulatorServer, RegisterImage
    from mbmon.io.exchanges import recorded_exchanges
    from mbmon.io.mcap.reader import LogError

    try:
        image = RegisterImage.from_exchanges(
            recorded_exchanges(log, keep),
            miss_exception=args.miss_exception if args.miss_exception is not None else 2,
            state=args.state or "follow",
        )
    except LogError as exc:
        err(str(exc))
        return EXIT_BAD_INPUT
    if not log.status.finished:
        err(f"note: {log.path}: {log.status.describe()}")
    if not image.units:
        err(f"error: {log.path}: no answered requests to learn the server from")
        return EXIT_BAD_INPUT
    server = EmulatorServer(image, host, port)

    def ready(h: str, p: int) -> None:
        known = ", ".join(
            f"{sum(len(v) for (_u, t), v in image.tables.items() if t == table)} {name}"
            for table, name in TABLE_NAMES.items()
        )
        units = ", ".join(str(u) for u in image.units)
        err(f"replay: serving {log.path.name} on {h}:{p} as the recorded server "
            f"(units {units}; {known}); Ctrl-C ends")  # fmt: skip

    async def main() -> None:
        stop = asyncio.Event()
        with loop_stops_on_signals(asyncio.get_running_loop(), lambda _n: stop.set()):
            await server.serve(stop, ready)

    try:
        asyncio.run(main())
    except OSError as exc:
        err(f"error: cannot listen on {host}:{port}: {exc.strerror or exc}")
        return EXIT_BAD_INPUT
    misses = image.miss_report()
    total = image.missed
    err(f"replay: {server.connections} client connection(s), {image.answered} requests "
        f"answered from the log, {total} not (exception {image.miss_exception:02X})")  # fmt: skip
    if misses:
        err("requests the log could not answer:")
        for line in misses:
            print(f"  {line}", file=sys.stderr)
    sys.stderr.flush()
    return exit_status(until_signal=True)  # Ctrl-C or SIGTERM is how it ends: 0


def _resend(args: argparse.Namespace, log: Any, keep: Any, host: str, port: int) -> int:
    from mbmon.io.exchanges import recorded_exchanges
    from mbmon.io.mcap.reader import LogError
    from mbmon.io.resend import LiveClient, LiveError, ResendReport, resend

    target = f"{host}:{port}"
    timeout = args.answer_timeout if args.answer_timeout is not None else 3.0
    try:
        client = LiveClient(host, port, timeout)
    except LiveError as exc:
        err(f"error: {exc}")
        return EXIT_BAD_INPUT
    if args.writes:
        err(f"warning: --writes: the recorded writes are sent to {target}")
    report = ResendReport()
    failed = interrupted = False
    out = sys.stdout
    try:
        report = resend(
            recorded_exchanges(log, keep),
            client,
            writes=args.writes,
            speed=args.speed,
            out=out,
            report=report,
        )
    except LogError as exc:
        err(str(exc))
        failed = True
    except LiveError as exc:
        err(f"error: {exc}")
        failed = True
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the summary still prints
        interrupted = True
    finally:
        client.close()
    for line in report.summary(target, args.writes):
        out.write(line + "\n")
    out.flush()
    status = exit_status(interrupted=interrupted, failed=failed)
    if status == EXIT_OK and not log.status.finished:
        err(f"note: {log.path}: {log.status.describe()}")
    if status == EXIT_OK and report.different:
        return EXIT_DIFFERENT
    return status
