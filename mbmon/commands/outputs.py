"""What a command opens before its run: the annotator, the view and filter, the
``-w`` logs (rotation, triggers), the Foxglove feed, and the words for an endpoint
that cannot be opened.

Re-exported by :mod:`mbmon.commands.common`. Failures to open are
:class:`~mbmon.sinks.base.SinkError` (exit 1) or
:class:`~mbmon.commands.ending.UsageError` (exit 2), raised before anything starts.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from mbmon.commands.ending import EXIT_USAGE, UsageError, err
from mbmon.commands.values import split_host_port


def make_annotator(specs: list[str]) -> Any:
    """The annotator for ``--profile`` values (``None`` without); bad specs are usage errors.
    Without a profile nothing of :mod:`mbmon.semantics` is imported (a run's fixed cost)."""
    if not specs:
        return None
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


def open_logs(targets: Iterable[str], ctx: Any, args: argparse.Namespace) -> list[Any]:
    """One listener per ``-w`` target (:func:`open_log`), in order. When one cannot be
    opened (:class:`~mbmon.sinks.base.SinkError`), or a signal comes meanwhile, those
    opened before it are closed (none is left half written) and the exception goes on."""
    logs: list[Any] = []
    try:
        for target in targets:
            logs.append(open_log(target, ctx, args))
    except BaseException:
        for sink in logs:
            sink.close()
        raise
    return logs


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
