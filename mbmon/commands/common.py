"""What every command shares: exit codes, usage errors, option groups, progress, outputs.

Commands are wiring (DESIGN): they parse options with these groups, build a
:class:`~mbmon.hub.Hub`, attach listeners and sources, and map the run's
outcome to one of the exit codes below.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

EXIT_OK = 0
EXIT_BAD_INPUT = 1  # bad or damaged input, or an output that failed
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class UsageError(Exception):
    """Bad command-line values; printed with the command's usage, exit status 2."""


# --------------------------------------------------------------------------- value types


def whole_number(what: str, lowest: int, highest: int, noun: str = "") -> Callable[[str], int]:
    """An argparse type for a whole number ``lowest..highest`` (decimal or ``0x``):
    the one home of integer option checks. Errors say "not a {noun or what}" and
    "{what} out of range"."""

    def parse(text: str) -> int:
        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a {noun or what}: {text!r}") from None
        if not lowest <= value <= highest:
            raise argparse.ArgumentTypeError(f"{what} out of range {lowest}..{highest}: {value}")
        return value

    parse.__name__ = what  # argparse names the type in some messages
    return parse


#: A TCP/UDP port 1..65535.
port = whole_number("port", 1, 65535, "port number")
#: A Modbus unit id of a server (1..247).
unit_id = whole_number("unit id", 1, 247)
#: A Modbus exception code mbmon answers with.
exception_code = whole_number("exception code", 1, 255)


def positive(text: str) -> float:
    """An argparse type: a number > 0 (seconds, speeds)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0 or value != value or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0: {text}")
    return value


def positive_int(text: str) -> int:
    """An argparse type: a whole number > 0 (baud rates, counts)."""
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {value}")
    return value


def endpoint(text: str) -> str:
    """An argparse type: ``HOST``, ``HOST:PORT``, ``[IPv6]:PORT`` or a serial device name."""
    value = text.strip()
    if not value or any(c.isspace() for c in value):
        raise argparse.ArgumentTypeError(f"not an endpoint: {text!r} (use HOST or HOST:PORT)")
    if value.startswith("/"):
        return value  # an RTU bus (serial device or dump file name)
    if value.startswith("["):
        close = value.find("]")
        if close < 0 or (close + 1 < len(value) and value[close + 1] != ":"):
            raise argparse.ArgumentTypeError(f"not an endpoint: {text!r} (use [ADDR]:PORT)")
        rest = value[close + 2 :] if close + 1 < len(value) else ""
    elif value.count(":") == 1:
        host, _, rest = value.partition(":")
        if not host:
            raise argparse.ArgumentTypeError(f"not an endpoint: {text!r} (no host)")
    else:
        rest = ""
    if rest:
        port(rest)  # raises with a clear message
    return value


def split_host_port(
    text: str, *, default_host: str | None = None, lowest: int = 1
) -> tuple[str, int]:
    """The one parser of socket addresses given on the command line: ``HOST:PORT``,
    ``[IPv6]:PORT``, or a bare ``PORT`` when ``default_host`` is given (listen
    addresses: loopback). ``lowest`` is 0 where port 0 (any free port) makes sense.
    Raises ``ValueError`` with the reason."""
    value = text.strip()
    host: str
    if value.startswith("["):
        host, sep, port_text = value[1:].partition("]:")
        if not sep:
            raise ValueError("use [ADDR]:PORT for IPv6")
    elif ":" in value:
        host, _, port_text = value.rpartition(":")
    elif default_host is not None:
        host, port_text = default_host, value
    else:
        raise ValueError("use HOST:PORT")
    if not host:
        if default_host is None:
            raise ValueError("the host is missing")
        host = default_host
    if any(c.isspace() for c in host):
        raise ValueError("not a host name")
    try:
        number = int(port_text, 10)
    except ValueError:
        raise ValueError("not a port number") from None
    if not lowest <= number <= 65535:
        raise ValueError(f"port out of range {lowest}..65535")
    return host, number


def parse_address(
    text: str, what: str, *, default_host: str | None = None, lowest: int = 1
) -> tuple[str, int]:
    """:func:`split_host_port` for an option checked after parsing: a bad address is
    a :class:`UsageError` naming the option (``--upstream 'x': use HOST:PORT``)."""
    try:
        return split_host_port(text, default_host=default_host, lowest=lowest)
    except ValueError as exc:
        raise UsageError(f"{what} {text.strip()!r}: {exc}") from None


def listen_address(text: str) -> tuple[str, int]:
    """An argparse type for where a server of mbmon listens: ``[HOST:]PORT``, a bare
    PORT on 127.0.0.1, port 0 for a free one."""
    try:
        return split_host_port(text, default_host="127.0.0.1", lowest=0)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: {exc}") from None


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
        "(repeatable)",
    )
    group.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="print no records and no summary (use with -w)",
    )


def add_live_options(group: Any) -> None:
    """``--plain``: the choice between the live screen and plain lines (live commands)."""
    group.add_argument(
        "--plain",
        action="store_true",
        help="one line per record instead of the live screen (the default when stdout "
        "is not a terminal)",
    )


# --------------------------------------------------------------------------- shared steps


class Interrupted(KeyboardInterrupt):
    """The run was stopped by SIGINT (Ctrl-C) or SIGTERM: ``signum`` says which.

    A ``KeyboardInterrupt``, so every ``except KeyboardInterrupt`` that finishes a
    run (logs closed, summary, "interrupted; LOG was finished") treats both
    signals alike."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


#: the signals :func:`install_signal_handlers` turned into :class:`Interrupted`, in order
_received: list[int] = []


#: a signal that came while the import system ran, to be raised a moment later
_deferred: list[int] = []


def _importing(frame: Any) -> bool:
    """Whether ``frame`` runs inside an import (the import system is on its stack)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _interrupt(signum: int, frame: Any) -> None:
    if _importing(frame):
        # raised inside an import, the exception can be swallowed by the import
        # system ("Exception ignored in ... _get_module_lock") or crash an extension
        # module's initialisation: raise it once the import is over (retried every 5 ms)
        _deferred.append(signum)
        signal.setitimer(signal.ITIMER_REAL, 0.005)
        return
    _received.append(signum)
    raise Interrupted(signum)


def _retry(signum: int, frame: Any) -> None:
    if _deferred:
        _interrupt(_deferred.pop(0), frame)


def install_signal_handlers() -> None:
    """SIGINT and SIGTERM end the run the same way, through one handler: it raises
    :class:`Interrupted` (a ``KeyboardInterrupt``), so every listener's close() runs
    and the command's own Ctrl-C ending (summary, message) follows either signal.
    A signal that comes during an import is raised when the import is over
    (retried every 5 ms through SIGALRM); an ignored signal stays ignored."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:  # nohup, a background job: kept
            signal.signal(sig, _interrupt)
    signal.signal(signal.SIGALRM, _retry)


def interrupted_status() -> int:
    """The exit status of a run a signal ended: 128 + its number (130 Ctrl-C, 143 SIGTERM)."""
    return 128 + (_received[0] if _received else signal.SIGINT)


def make_annotator(specs: list[str]) -> Any:
    """The annotator for ``--profile`` values (``None`` without); bad specs are usage errors."""
    from mbmon.semantics.annotate import annotator_for
    from mbmon.semantics.profile import ProfileError

    try:
        return annotator_for(specs)
    except ProfileError as exc:
        raise UsageError(str(exc)) from None


def view_and_filter(args: argparse.Namespace) -> tuple[Any, Any]:
    """The view (``--robot``, ``--robot-client``, ``-t``) and the display filter
    (``--unit --fc --address --since --until --grep``) of a command that prints
    records as they come (``read``, ``sniff``); a bad filter is a usage error."""
    from mbmon.filters import FilterError, build_filter
    from mbmon.format import View
    from mbmon.timefmt import TimeFormat

    view = View(
        robot=args.robot,
        robot_is_client=args.robot_client,
        time_format=TimeFormat(args.time_format),
    )
    try:
        flt = build_filter(args, time_format=view.time_format, start_known=False)
    except FilterError as exc:
        raise UsageError(str(exc)) from None
    return view, flt


def profile_sources(annotator: Any) -> list[tuple[str, str]]:
    """``(name, TOML text)`` of every profile the annotator loaded (for logs)."""
    if annotator is None:
        return []
    binding = getattr(annotator, "binding", None)
    sources = getattr(binding, "sources", None)
    return list(sources()) if callable(sources) else []


def check_outputs(outputs: Iterable[str], inputs: Iterable[str]) -> None:
    """Refuse, as a usage error, an output with no known format or one that is an input.

    "The same file" is the same device and inode, so links and other spellings
    of a path are caught too; an output that does not exist yet is never an input.
    """
    from mbmon.sinks.base import SINKS

    in_stats = []
    for name in inputs:
        try:
            in_stats.append((name, os.stat(name)))
        except OSError:
            continue
    for out in outputs:
        suffix = Path(out).suffix.lower()
        if suffix not in SINKS:
            known = ", ".join(sorted(SINKS))
            raise UsageError(
                f"{out}: unknown output format {suffix or '(no suffix)'!r}; use one of {known}"
            )
        try:
            st = os.stat(out)
        except OSError:
            continue
        for name, ist in in_stats:
            if (st.st_dev, st.st_ino) == (ist.st_dev, ist.st_ino):
                raise UsageError(f"{out}: is the input {name}; refusing to overwrite it")


class Progress:
    """A rich progress bar on stderr for long work, only when stderr is a terminal.

    It never takes stdout: records go to stdout, progress to stderr.
    """

    MIN_BYTES = 4 << 20  # about a second of reading

    def __init__(self, label: str, enabled: bool | None = None):
        self._bar: Any = None
        self._task: Any = None
        self._label = label
        self._enabled = sys.stderr.isatty() if enabled is None else enabled

    def __call__(self, done: int, total: int) -> None:
        if not self._enabled or total < self.MIN_BYTES:
            return
        if self._bar is None:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                DownloadColumn,
                Progress,
                TextColumn,
                TimeRemainingColumn,
            )

            self._bar = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                DownloadColumn(),
                TimeRemainingColumn(),
                console=Console(stderr=True),
                transient=True,
                redirect_stdout=False,
                redirect_stderr=False,
            )
            self._bar.start()
            self._task = self._bar.add_task(self._label, total=total)
        self._bar.update(self._task, completed=done)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


def err(message: str) -> None:
    """One line on stderr, prefixed like every mbmon message."""
    print(f"mbmon: {message}", file=sys.stderr, flush=True)


def wants_state_panel(profile_specs: Iterable[str]) -> bool:
    """Whether the live monitor shows the HRSS state panel: an ``hrss`` profile is in use."""
    return any("hrss" in spec for spec in profile_specs)


class Figures:
    """A hub listener that feeds a command's own figures (kernel drops, bus health,
    proxy clients and refusals) to the live monitor on every tick.

    ``source()`` returns the figures (name -> value); it runs in the hub's thread.
    """

    name = "figures"

    def __init__(self, monitor: Any, source: Any) -> None:
        self.monitor = monitor
        self.source = source

    def on_tick(self, now: float) -> None:
        self.monitor.set_figures(self.source())


def open_console(
    args: argparse.Namespace, view: Any, *, title: str, annotator: Any = None
) -> tuple[Any, Any]:
    """The one place a live command decides what goes to the terminal.

    Returns ``(listener, monitor)``: nothing with ``-q``; plain lines
    (:class:`~mbmon.sinks.console.ConsoleListener`) with ``--json``, ``--plain`` or
    when stdout is not a terminal; otherwise the rich live monitor, which is then
    both the listener and the monitor (for figures a command feeds it). With the
    run's ``annotator``, the monitor's state panel shows the HRSS sessions' written
    parameter registers (R200..R251).
    """
    if args.quiet:
        return None, None
    if args.json or getattr(args, "plain", False) or not sys.stdout.isatty():
        from mbmon.sinks.console import ConsoleListener

        return ConsoleListener(sys.stdout, view, as_json=args.json, live=True), None
    from mbmon.sinks.live import LiveMonitor

    profiles = getattr(args, "profile", []) or []
    monitor = LiveMonitor(
        view, title=title, state_panel=wants_state_panel(profiles), annotator=annotator
    )
    return monitor, monitor


# --------------------------------------------------------------------------- Foxglove live

#: ``--foxglove`` without a value: Foxglove's default port, on loopback
FOXGLOVE_DEFAULT = ("127.0.0.1", 8765)


def foxglove_address(text: str) -> tuple[str, int]:
    """An argparse type: ``[HOST:]PORT`` (``[IPv6]:PORT`` too) -> ``(host, port)``.

    A bare PORT listens on 127.0.0.1; port 0 picks a free port.
    """
    try:
        return split_host_port(text, default_host=FOXGLOVE_DEFAULT[0], lowest=0)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"not [HOST:]PORT: {text!r} ({exc}; an interface goes before --foxglove)"
        ) from None


def add_foxglove_option(group: Any) -> None:
    """``--foxglove [HOST:]PORT``: serve the run live to Foxglove (any observing command)."""
    group.add_argument(
        "--foxglove",
        nargs="?",
        const=FOXGLOVE_DEFAULT,
        default=None,
        type=foxglove_address,
        metavar="[HOST:]PORT",
        help="serve the log's topics live over Foxglove's WebSocket protocol "
        "(default 127.0.0.1:8765; PORT alone listens on 127.0.0.1, 0 picks a free port; "
        "name a host such as 0.0.0.0 to open it to the network). Needs "
        "pip install 'mbmon[foxglove]'",
    )


def open_foxglove(args: argparse.Namespace, ctx: Any) -> Any:
    """Start the live Foxglove feed that ``--foxglove`` asks for (``None`` without it).

    ``ctx`` is the run's :class:`~mbmon.sinks.base.SinkContext` (view, source,
    profiles: the feed serves the topics a log of the run would have). Says on
    stderr where it listens and how to connect. Attach the result to the hub as
    a listener (before the console, like the logs) and let ``hub.close()`` close it.

    A port that cannot be bound raises :class:`~mbmon.sinks.base.SinkError`
    (report it as any output that cannot open: one line, exit 1). Without the
    ``foxglove-sdk`` package it says so in one line and exits with status 2:
    call it before opening any file, so nothing is left half written.
    """
    address = getattr(args, "foxglove", None)
    if address is None:
        return None
    from mbmon.sinks.foxglove import FeedUnavailable, FoxgloveFeed

    host, number = address
    try:
        feed = FoxgloveFeed(ctx, host, number)
    except FeedUnavailable as exc:
        err(str(exc))
        raise SystemExit(EXIT_USAGE) from None
    where = (
        ""
        if host in ("127.0.0.1", "::1", "localhost")
        else (" (reachable from the network: anyone who can connect sees the traffic)")
    )
    err(
        f"Foxglove live feed on {feed.url}{where}; in Foxglove: Open connection → "
        f"Foxglove WebSocket → {feed.url}"
    )
    return feed
