"""Command-line entry point: parser assembly, ``main()``, and what ends a run.

Every command is a module of :mod:`mbmon.commands` (``register`` adds its
parser, ``run`` wires sources, hub and listeners); the log commands are in
:mod:`mbmon.commands.logs`. Exit codes are defined once, in
:mod:`mbmon.commands.common`.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable

from mbmon import __version__
from mbmon.commands import COMMANDS
from mbmon.commands.common import (
    EXIT_BAD_INPUT,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    UsageError,
    install_signal_handlers,
    make_annotator,
)

__all__ = ["EXIT_BAD_INPUT", "EXIT_OK", "EXIT_USAGE", "build_parser", "main", "make_annotator"]


def build_parser() -> argparse.ArgumentParser:
    """The ``mbmon`` parser with every command's sub-parser."""
    parser = argparse.ArgumentParser(
        prog="mbmon",
        description="Modbus RTU/TCP analyzer and monitor for HIWIN robot cells: shows what "
        "crosses the wire between a PLC and a robot, and what it means.",
        epilog="Run 'mbmon COMMAND --help' for the options and examples of each command.",
    )
    parser.add_argument("--version", action="version", version=_version())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS[:2]:  # read, decode
        importlib.import_module(f"mbmon.commands.{name}").register(sub)
    from mbmon.commands import logs

    logs.add_subcommands(sub)
    for name in COMMANDS[2:]:
        importlib.import_module(f"mbmon.commands.{name}").register(sub)
    return parser


def _version() -> str:
    """``mbmon --version``: the version and which core is active (compiled or pure Python)."""
    from mbmon import core

    return f"mbmon {__version__} ({core.status()})"


def main(argv: list[str] | None = None) -> int:
    """Run one command; every failure ends in a message and an exit code, not a traceback."""
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return EXIT_USAGE
    from mbmon.sinks.base import SinkError

    install_signal_handlers()
    if hasattr(sys.stdout, "reconfigure"):
        # a terminal that cannot show "→" or "°" gets \u2192 escapes (valid inside JSON
        # strings too) instead of a traceback
        sys.stdout.reconfigure(errors="backslashreplace")
    try:
        return func(args)
    except UsageError as exc:
        command_parser = _subparser(parser, args.command)
        command_parser.print_usage(sys.stderr)
        command_parser.exit(EXIT_USAGE, f"mbmon {args.command}: error: {exc}\n")
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # stdout closed early (e.g. `mbmon read big.pcap | head`): stop quietly.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    except SinkError as exc:  # an output failed while running (disk full, ...)
        print(f"mbmon: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:  # stdout or an output file failed while running
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"mbmon: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    return EXIT_OK


def _subparser(parser: argparse.ArgumentParser, name: str | None) -> argparse.ArgumentParser:
    """The sub-parser of command ``name`` (its usage line is what a usage error shows)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and name in action.choices:
            return action.choices[name]
    return parser


if __name__ == "__main__":
    sys.exit(main())
