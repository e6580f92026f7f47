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


#: how many 5-ms retries a deferred signal waits for an import to end (then it is raised)
_MAX_RETRIES = 40
_retries: list[int] = [0]


def _interrupt(signum: int, frame: Any) -> None:
    if _importing(frame) and _retries[0] < _MAX_RETRIES:
        _retries[0] += 1
        # raised inside an import, the exception can be swallowed by the import
        # system ("Exception ignored in ... _get_module_lock") or crash an extension
        # module's initialisation: raise it once the import is over (retried every 5 ms)
        _deferred.append(signum)
        signal.setitimer(signal.ITIMER_REAL, 0.005)
        return
    _received.append(signum)
    signal.setitimer(signal.ITIMER_REAL, 0)  # a deferred retry still pending is this one
    _deferred.clear()
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


def open_log(target: str, ctx: Any, args: argparse.Namespace) -> Any:
    """The listener for one ``-w`` target: the format's sink, or with ``--rotate``
    a ring of them (:class:`mbmon.analysis.rotate.RotatingSink`). Raises
    :class:`~mbmon.sinks.base.SinkError` when it cannot be opened and
    :class:`UsageError` for bad ``--rotate``/``--keep`` values."""
    from mbmon.sinks.base import open_sink

    rotation = check_rotation(args)
    if rotation is None:
        if getattr(args, "trigger", None) is None:
            return open_sink(target, ctx)
        rotation = (None, None)  # each trigger window is a file of the ring
    from mbmon.analysis.rotate import RotatingSink

    every, size = rotation
    return RotatingSink(target, ctx, every=every, max_bytes=size, keep=args.keep)


def check_rotation(args: argparse.Namespace) -> tuple[float | None, int | None] | None:
    """``--rotate`` as ``(seconds, bytes)``, or ``None`` without it; bad values, and
    ``--keep`` or ``--rotate`` without ``-w``/``--keep`` without ``--rotate``, are
    usage errors. Call it before anything starts."""
    rotate = getattr(args, "rotate", None) or []
    keep = getattr(args, "keep", None)
    if not rotate:
        if keep is not None and getattr(args, "trigger", None) is None:
            raise UsageError("--keep needs --rotate or --trigger")
        return None
    if not getattr(args, "write", None):
        raise UsageError("--rotate needs -w FILE")
    from mbmon.analysis.rotate import RotationError, parse_rotate

    try:
        return parse_rotate(rotate)
    except RotationError as exc:
        raise UsageError(str(exc)) from None


def open_trigger(args: argparse.Namespace) -> Any:
    """The :class:`~mbmon.analysis.trigger.TriggerGate` that ``--trigger`` asks for
    (``None`` without it), telling each window on stderr; bad values are usage
    errors. Add the logs and the screen to it, then it to the hub."""
    text = getattr(args, "trigger", None)
    if text is None:
        for name in ("before", "after"):
            if getattr(args, name, None) not in (None, "30s", "10s"):
                raise UsageError(f"--{name} needs --trigger")
        return None
    from mbmon.analysis.trigger import TriggerGate
    from mbmon.filters import FilterError, parse_expression
    from mbmon.sinks.csvfile import utc_text
    from mbmon.timefmt import TimeParseError, parse_duration

    try:
        expression = parse_expression(text)
    except FilterError as exc:
        raise UsageError(f"--trigger: {exc}") from None
    spans = []
    for name in ("before", "after"):
        try:
            spans.append(parse_duration(getattr(args, name)))
        except TimeParseError as exc:
            raise UsageError(f"--{name}: {exc}") from None

    def told(number: int, window: Any) -> None:
        err(
            f"trigger window {number}: {utc_text(window.start)} .. {utc_text(window.end)} "
            f"({window.triggers} trigger{'s' if window.triggers != 1 else ''}; first: "
            f"{window.what})"
        )

    return TriggerGate(expression, spans[0], spans[1], on_window=told)


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


def why_not(exc: OSError, port: int | None = None) -> str:
    """The system's reason an endpoint cannot be opened, in words, with a hint where one
    helps (``port``: the TCP port that was asked for). One home for the words of
    :func:`listen_error` and :func:`serial_open_error`."""
    import errno as errnos

    reason = exc.strerror or str(exc) or type(exc).__name__
    code = exc.errno
    if port is not None and code:  # asyncio words a bind error as a sentence around it
        reason = os.strerror(code)
    if code == errnos.EADDRINUSE:
        return f"{reason} (another program listens there; pick another port)"
    if code in (errnos.EACCES, errnos.EPERM) and port is not None and 0 < port < 1024:
        return (
            f"{reason} (port {port} is privileged: ports below 1024 need root or "
            "CAP_NET_BIND_SERVICE; use a port from 1024 up, e.g. 1502)"
        )
    if code == errnos.EADDRNOTAVAIL:
        return f"{reason} (no interface of this machine has that address)"
    if code == errnos.ENOENT and port is None:
        return f"{reason} (no such device: is the adapter plugged in, the name right?)"
    if code in (errnos.EACCES, errnos.EPERM) and port is None:
        return f"{reason} (add yourself to the group that owns the device, e.g. dialout)"
    return reason


def listen_error(where: str, exc: OSError, port: int | None = None) -> str:
    """The one message for a server that cannot listen on ``where`` (``HOST:PORT``)."""
    return f"cannot listen on {where}: {why_not(exc, port)}"


def serial_open_error(device: str, exc: OSError) -> str:
    """The one message for a serial port that cannot be opened."""
    return f"cannot open serial port {device}: {why_not(exc)}"


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
    when stdout or stdin is not a terminal; otherwise the interactive monitor's feed
    (:class:`~mbmon.monitor.feed.MonitorFeed`), which is then both the listener and
    the monitor (for figures a command feeds it, and for :func:`run_live`). With the
    run's ``annotator``, the robot panel shows the HRSS sessions' written parameter
    registers (R200..R251).
    """
    if args.quiet:
        return None, None
    if args.json or getattr(args, "plain", False) or not _interactive():
        from mbmon.sinks.console import ConsoleListener

        return ConsoleListener(sys.stdout, view, as_json=args.json, live=True), None
    from mbmon.monitor.feed import MonitorFeed

    profiles = getattr(args, "profile", []) or []
    monitor = MonitorFeed(
        view, title=title, profile=wants_state_panel(profiles), annotator=annotator
    )
    return monitor, monitor


def _interactive() -> bool:
    """Whether the screen can run: stdout is a terminal, and so is stdin (its keys)."""
    try:
        return sys.stdout.isatty() and sys.stdin is not None and sys.stdin.isatty()
    except (AttributeError, ValueError):
        return False


def filter_text(args: argparse.Namespace) -> str:
    """The command-line filters (``--unit --fc --address --since --until --grep``) as
    the monitor's display filter, in the same syntax (``f`` on the screen edits it)."""
    import shlex

    parts: list[str] = []
    for unit in getattr(args, "unit", None) or []:
        parts += ["--unit", unit]
    for fc in getattr(args, "fc", None) or []:
        parts += ["--fc", fc]
    for name in ("address", "since", "until", "grep"):
        value = getattr(args, name, None)
        if value:
            parts += [f"--{name}", value]
    return shlex.join(parts)


def run_live(monitor: Any, work: Any, stop: Any, **screen: Any) -> None:
    """Run ``work`` (a live command's hub loop): here without a monitor, else in a thread
    of its own under the interactive screen (:func:`mbmon.monitor.run_screen`, which
    takes ``screen``'s keywords), which ``stop`` ends as Ctrl-C would."""
    if monitor is None:
        work()
        return
    from mbmon.monitor import run_screen

    run_screen(monitor, work, stop, **screen)


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
