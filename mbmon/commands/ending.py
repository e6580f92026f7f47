"""How a run ends: the exit codes, the one signal handler and the one exit-status decision.

Every command ends through here (re-exported by :mod:`mbmon.commands.common`):

- :func:`install_signal_handlers` (``mbmon.cli.main`` calls it once): SIGINT and
  SIGTERM raise :class:`Interrupted`, a ``KeyboardInterrupt``, in the main thread.
  A command that reads until its input ends (``read``, ``replay``, ``export``,
  ``report``) catches ``KeyboardInterrupt`` around its hub loop, lets the
  listeners close, prints its summary and returns :func:`exit_status`.
- :func:`stop_on_signals` (a ``with`` block): a command that runs until it is
  stopped (``sniff``, ``proxy``, ``demo``, ``sim``, the servers of ``replay``)
  gets a call instead of an exception: it stops its sources, the hub drains and
  closes, nothing is cut in the middle. The raising handler comes back when the
  block ends.
- :func:`exit_status`: one decision for every command, from the hub's failures
  and errors, the signal that came (if one did) and the command's own verdict.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

EXIT_OK = 0
EXIT_BAD_INPUT = 1  # bad or damaged input, or an output that failed
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


class UsageError(Exception):
    """Bad command-line values; printed with the command's usage, exit status 2."""


def err(message: str) -> None:
    """One line on stderr, prefixed like every mbmon message."""
    print(f"mbmon: {message}", file=sys.stderr, flush=True)


#: the signals that end a run, alike
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """The run was stopped by SIGINT (Ctrl-C) or SIGTERM: ``signum`` says which.

    A ``KeyboardInterrupt``, so every ``except KeyboardInterrupt`` that finishes a
    run (logs closed, summary, "interrupted; LOG was finished") treats both
    signals alike."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


#: every SIGINT/SIGTERM that reached one of mbmon's handlers in this run, in order
_received: list[int] = []

#: a signal received but not raised yet: it came while the import system ran, or its
#: exception was swallowed where Python ignores exceptions; raised a moment later
_deferred: list[int] = []

#: how often a deferred signal looks again whether it can be raised (SIGALRM), seconds
RETRY_EVERY = 0.005
#: how long a signal waits at most for an import to end before it is raised inside it
MAX_DEFER = 5.0
#: when the signal now deferred first came (``time.monotonic()``)
_deferred_since: list[float] = []


def _importing(frame: Any) -> bool:
    """Whether ``frame`` runs inside an import (the import system is on its stack)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _defer(signum: int) -> None:
    """Raise ``signum``'s :class:`Interrupted` :data:`RETRY_EVERY` from now (SIGALRM)."""
    if not _deferred:
        _deferred.append(signum)
    if not _deferred_since:
        _deferred_since.append(time.monotonic())
    signal.setitimer(signal.ITIMER_REAL, RETRY_EVERY)


def _interrupt(signum: int, frame: Any) -> None:
    """The one handler of SIGINT and SIGTERM (:func:`install_signal_handlers`)."""
    _received.append(signum)  # recorded first: whatever happens next, the run knows
    _raise(signum, frame)


def _raise(signum: int, frame: Any) -> None:
    waited = time.monotonic() - _deferred_since[0] if _deferred_since else 0.0
    if _importing(frame) and waited < MAX_DEFER:
        # raised inside an import, the exception can be swallowed by the import
        # system ("Exception ignored in ... _get_module_lock") or crash an extension
        # module's initialisation: raise it once the import is over
        _defer(signum)
        return
    signal.setitimer(signal.ITIMER_REAL, 0)  # a deferred retry still pending is this one
    _deferred.clear()
    _deferred_since.clear()
    raise Interrupted(signum)


def _retry(signum: int, frame: Any) -> None:
    if _deferred:
        _raise(_deferred.pop(0), frame)


def _unraisable(args: Any) -> None:
    """``sys.unraisablehook`` while the handlers are installed: an :class:`Interrupted`
    raised where Python ignores exceptions (a finalizer, a weakref callback, a
    generator closed by the garbage collector) would be printed ("Exception ignored
    in ...") and lost, and the run would go on as if no signal came: it is raised
    again a moment later, in the code that runs then. Anything else goes to the
    hook that was there before."""
    if isinstance(args.exc_value, Interrupted):
        _defer(args.exc_value.signum)
        return
    _previous_unraisablehook[0](args)


_previous_unraisablehook: list[Callable[[Any], Any]] = [sys.unraisablehook]


def install_signal_handlers() -> None:
    """SIGINT and SIGTERM end the run the same way, through one handler: it raises
    :class:`Interrupted` (a ``KeyboardInterrupt``) in the main thread, so every
    listener's close() runs and the command's own Ctrl-C ending (summary, message)
    follows either signal.

    A signal is never lost: it is recorded the moment it comes (:func:`exit_status`
    answers 128 + its number even if a command never saw the exception); one that
    comes during an import is raised when the import is over (looked at again
    every :data:`RETRY_EVERY` s through SIGALRM, for :data:`MAX_DEFER` s at most);
    one whose exception Python swallowed (raised inside a finalizer or a weakref
    callback) is raised again a moment later. An ignored signal stays ignored.
    Forgets the signals of an earlier run in this process."""
    _received.clear()
    _deferred.clear()
    _deferred_since.clear()
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:  # nohup, a background job: kept
            signal.signal(sig, _interrupt)
    signal.signal(signal.SIGALRM, _retry)
    if sys.unraisablehook is not _unraisable:
        _previous_unraisablehook[0] = sys.unraisablehook
        sys.unraisablehook = _unraisable


def received_signal() -> int | None:
    """The first SIGINT/SIGTERM that reached mbmon's handlers in this run, or ``None``."""
    return _received[0] if _received else None


def pending_signal() -> int | None:
    """A signal that came but whose :class:`Interrupted` was not raised yet (it came
    during an import, or Python swallowed it): ``mbmon.cli.main`` asks when a command
    returns, so a signal that came as the run ended still ends it with 128 + its
    number instead of being dropped with the retry timer."""
    return _deferred[0] if _deferred else None


def interrupted_status() -> int:
    """The exit status of a run a signal ended: 128 + its number (130 Ctrl-C, 143 SIGTERM)."""
    return 128 + (_received[0] if _received else signal.SIGINT)


class SignalStop:
    """What :func:`stop_on_signals` hands its block: the signals that came during it."""

    def __init__(self) -> None:
        self.received: list[int] = []

    @property
    def count(self) -> int:
        """How many SIGINT/SIGTERM came (a second one: stop waiting for anything)."""
        return len(self.received)

    @property
    def signum(self) -> int | None:
        """The first signal that came, or ``None``."""
        return self.received[0] if self.received else None


@contextmanager
def stop_on_signals(stop: Callable[[int], None]) -> Iterator[SignalStop]:
    """For a command that runs until it is stopped: inside the block SIGINT and SIGTERM
    call ``stop(n)`` (``n`` = how many signals came so far: 1, then 2 for a second
    Ctrl-C, which should stop waiting for anything) instead of raising; the signal
    is recorded for :func:`exit_status`. ``stop`` runs in the main thread between
    two bytecodes: it must only ask (set an event, ``hub.stop()``, an engine's
    ``stop()``), never block or raise. The previous handlers (the raising ones of
    :func:`install_signal_handlers`) come back when the block ends, so a signal
    during the closing summary still ends the run. An ignored signal stays
    ignored; outside the main thread this installs nothing."""
    state = SignalStop()
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    def on_signal(signum: int, frame: object) -> None:
        state.received.append(signum)
        _received.append(signum)
        stop(len(state.received))

    old = {}
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            old[sig] = signal.signal(sig, on_signal)
    try:
        yield state
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


@contextmanager
def loop_stops_on_signals(loop: Any, stop: Callable[[int], None]) -> Iterator[SignalStop]:
    """:func:`stop_on_signals` for a command whose main thread runs an asyncio ``loop``
    (``sim``, ``replay --serve``): the loop's own signal handlers (woken through its
    self-pipe, whichever thread the signal reached) call ``stop(n)`` in the loop and
    record the signal; the handlers that were there before come back when the
    block ends. An ignored signal stays ignored; a loop that cannot take signal
    handlers (not the main thread) gets none."""
    state = SignalStop()

    def on_signal(signum: int) -> None:
        state.received.append(signum)
        _received.append(signum)
        stop(len(state.received))

    old: dict[int, Any] = {}
    for sig in STOP_SIGNALS:
        previous = signal.getsignal(sig)
        if previous is signal.SIG_IGN:
            continue
        try:
            loop.add_signal_handler(sig, on_signal, sig)
        except (NotImplementedError, RuntimeError, ValueError):
            continue
        old[sig] = previous
    try:
        yield state
    finally:
        for signum, handler in old.items():
            loop.remove_signal_handler(signum)
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)


def output_failed(hub: Any) -> bool:
    """Whether a listener of ``hub`` failed and was detached for any reason but a
    reader of stdout that went away (``| head``: a broken pipe is no failure)."""
    failures = getattr(hub, "failures", None) or []
    return any(why != "broken pipe" for _name, why in failures)


def exit_status(
    hub: Any = None,
    *,
    interrupted: bool = False,
    failed: bool = False,
    until_signal: bool = False,
) -> int:
    """The one exit status of a run, in this order:

    1. ``1`` (:data:`EXIT_BAD_INPUT`) when an output failed (:func:`output_failed`):
       a record may be missing from a log, whatever else happened;
    2. ``128 + signal`` (130 Ctrl-C, 143 SIGTERM) when a signal stopped the run
       (``interrupted``: the command caught ``KeyboardInterrupt``; or one reached a
       handler of :func:`install_signal_handlers` / :func:`stop_on_signals`), unless
       ``until_signal``: the command runs until it is stopped (``sniff``, ``proxy``,
       the servers), so a signal is its normal end;
    3. ``1`` when the input was bad (``failed``: the command's own verdict, or an
       error the hub recorded in ``hub.errors``);
    4. ``0``.

    It prints nothing: the command says why before it returns the status."""
    if hub is not None and output_failed(hub):
        return EXIT_BAD_INPUT
    if (interrupted or _received) and not until_signal:
        return interrupted_status()
    if failed or (hub is not None and getattr(hub, "errors", None)):
        return EXIT_BAD_INPUT
    return EXIT_OK
