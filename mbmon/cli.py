"""Command-line entry point: parser assembly, ``main()``, and what ends a run.

Every command is a module of :mod:`mbmon.commands` (``register`` adds its
parser, ``run`` wires sources, hub and listeners); the log commands are
:mod:`~mbmon.commands.replay`, :mod:`~mbmon.commands.info` and
:mod:`~mbmon.commands.export`. Exit codes are defined once, in
:mod:`mbmon.commands.common`.

Importing this module imports nothing else of mbmon and nothing heavy: the
console script imports it before :func:`main` runs, and a Ctrl-C that comes
while the commands are still being imported must meet :func:`main`'s handler
(exit 130, quietly), not a traceback.
"""

from __future__ import annotations

import _signal  # type: ignore[import-not-found]  # built in, no file to read: up first
import sys

#: SIGINT/SIGTERM that came while this module was being imported (see the module's end)
_EARLY: list[int] = []


def _note_early(signum: int, frame: object) -> None:
    _EARLY.append(signum)


_BEFORE: dict[int, object] = {}


def _take_signals() -> None:
    """The noting handler for SIGINT and SIGTERM (each once; an ignored one is kept)."""
    for sig in (_signal.SIGINT, _signal.SIGTERM):
        if sig in _BEFORE:
            continue
        was = _signal.getsignal(sig)
        if was is _signal.SIG_IGN:  # nohup, a background job: kept
            continue
        if was is _note_early:  # taken, but the previous handler was not noted yet
            was = _signal.default_int_handler if sig == _signal.SIGINT else _signal.SIG_DFL
        else:
            _signal.signal(sig, _note_early)
        _BEFORE[sig] = was


while True:
    try:
        _take_signals()
        break
    except ValueError:  # imported outside the main thread: signals are not this module's
        break
    except KeyboardInterrupt:  # a Ctrl-C before the noting handler was in place
        _EARLY.append(_signal.SIGINT)

import signal  # noqa: E402  (a module read from disk: a Ctrl-C may come meanwhile)

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing
if TYPE_CHECKING:
    import argparse
    from collections.abc import Sequence
    from typing import Any

    from mbmon.commands.common import EXIT_BAD_INPUT, EXIT_OK, EXIT_USAGE, make_annotator

__all__ = ["EXIT_BAD_INPUT", "EXIT_OK", "EXIT_USAGE", "build_parser", "main", "make_annotator"]

#: names this module re-exports from :mod:`mbmon.commands.common`, imported when first used
_COMMON = frozenset({"EXIT_BAD_INPUT", "EXIT_OK", "EXIT_USAGE", "make_annotator"})


def __getattr__(name: str) -> Any:
    if name in _COMMON:
        from mbmon.commands import common

        return getattr(common, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def build_parser(commands: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The ``mbmon`` parser with every command's sub-parser, or only those of ``commands``
    (:func:`_commands_needed`: a run parses one command's options and never the others')."""
    import argparse
    import importlib

    from mbmon.commands import COMMANDS

    parser = argparse.ArgumentParser(
        prog="mbmon",
        description="Modbus RTU/TCP analyzer and monitor for HIWIN robot cells: shows what "
        "crosses the wire between a PLC and a robot, and what it means.",
        epilog="Run 'mbmon COMMAND --help' for the options and examples of each command.",
    )
    parser.add_argument("--version", action=_version_action())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        if commands is None or name in commands:
            importlib.import_module(f"mbmon.commands.{name}").register(sub)
    return parser


def _version_action() -> type[argparse.Action]:
    """argparse's ``version`` action, its text made when ``--version`` is given: finding
    which core is active imports the compiled core, which no other run of the parser
    (``--help``, a command that does not read) needs."""
    import argparse

    class LazyVersion(argparse._VersionAction):
        def __call__(self, parser: argparse.ArgumentParser, *args: Any, **kwargs: Any) -> None:
            self.version = _version()
            super().__call__(parser, *args, **kwargs)

    return LazyVersion


def _version() -> str:
    """``mbmon --version``: the version and which core is active (compiled or pure Python)."""
    from mbmon import __version__, core

    return f"mbmon {__version__} ({core.status()})"


def main(argv: list[str] | None = None) -> int:
    """Run one command; every failure ends in a message and an exit code, not a traceback.

    SIGINT and SIGTERM end a run the same way from the first instant (also while
    the commands are being imported): quietly, with 128 + the signal's number
    (130, 143), after the command finished what it had open."""
    # until the commands are imported and the one handler is installed, a signal is
    # only noted: an exception raised inside the import system can be swallowed
    # ("Exception ignored in ... _get_module_lock") instead of ending the run
    noted: list[int] = []

    def note(signum: int, frame: object) -> None:
        noted.append(signum)

    previous = {}
    try:
        alarm = signal.getsignal(signal.SIGALRM)  # the deferred signals' retries use it
        # inside the try: a Ctrl-C landing while the noting handlers go in (Python's
        # default handler still in place) ends the run as one landing later does
        for sig in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(sig) is not signal.SIG_IGN:  # nohup, a background job: kept
                previous[sig] = signal.signal(sig, note)
        try:
            return _run(argv, noted)
        finally:
            # a deferred signal's retry must not outlive the run: at exit Python puts
            # SIGALRM back to its default action, which would kill the process (-14)
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, alarm if alarm is not None else signal.SIG_DFL)
            for sig, handler in previous.items():  # still noting (--help, usage): undo
                if signal.getsignal(sig) is note:
                    signal.signal(sig, handler)
    except KeyboardInterrupt as exc:  # not caught by the command, or as it ended
        return 128 + getattr(exc, "signum", signal.SIGINT)


def _run(argv: list[str] | None, noted: list[int]) -> int:
    import os

    from mbmon.commands.common import (
        EXIT_BAD_INPUT,
        EXIT_INTERRUPTED,
        EXIT_OK,
        EXIT_USAGE,
        UsageError,
        install_signal_handlers,
        interrupted_status,
        pending_signal,
    )

    parser = build_parser(_commands_needed(sys.argv[1:] if argv is None else argv))
    args = parser.parse_args(argv)
    install_signal_handlers()
    if noted:  # Ctrl-C or SIGTERM while starting: nothing has begun, nothing to finish
        return 128 + noted[0]
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return EXIT_USAGE

    if hasattr(sys.stdout, "reconfigure"):
        # a terminal that cannot show "→" or "°" gets \u2192 escapes (valid inside JSON
        # strings too) instead of a traceback
        sys.stdout.reconfigure(errors="backslashreplace")
    from mbmon.sinks.base import SinkError  # after parse_args: --help and usage never need it

    try:
        status: int = func(args)
    except UsageError as exc:
        command_parser = _subparser(parser, args.command)
        command_parser.print_usage(sys.stderr)
        command_parser.exit(EXIT_USAGE, f"mbmon {args.command}: error: {exc}\n")
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
    if status == EXIT_INTERRUPTED:  # a command that caught the signal and finished up
        return interrupted_status()
    if status == EXIT_OK and pending_signal() is not None:
        # the signal came in an import as the run ended, deferred past it: the run was
        # interrupted all the same (the retry timer is cancelled on the way out)
        return interrupted_status()
    return status


def _commands_needed(argv: Sequence[str]) -> list[str] | None:
    """The commands whose sub-parsers parsing ``argv`` can reach (``None``: all of them).

    ``mbmon COMMAND ...`` reaches only COMMAND's: argparse hands everything after the
    command's name to its sub-parser, and ``mbmon``'s own options (``-h``, ``--version``)
    come before it. ``mbmon --version`` alone reaches none: it prints and exits as the
    option is read. Anything else (``mbmon --help``, ``mbmon -h read``, no command, an
    unknown one) gets every command's sub-parser, as the listing and the errors name them."""
    from mbmon.commands import COMMANDS

    if not argv:
        return None
    if argv[0] in COMMANDS:
        return [argv[0]]
    if list(argv) == ["--version"]:
        return []
    return None


def _subparser(parser: argparse.ArgumentParser, name: str | None) -> argparse.ArgumentParser:
    """The sub-parser of command ``name`` (its usage line is what a usage error shows)."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and name in action.choices:
            return action.choices[name]
    return parser


# the module is imported: the handlers before it are back (main() installs its own);
# a signal that came meanwhile ends the run here, quietly, as main() would end it
for _sig, _handler in _BEFORE.items():
    if _signal.getsignal(_sig) is _note_early:
        _signal.signal(_sig, _handler if _handler is not None else _signal.SIG_DFL)
if _EARLY:
    raise SystemExit(128 + _EARLY[0])

if __name__ == "__main__":
    sys.exit(main())
