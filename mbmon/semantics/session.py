"""Device sessions: the stateful meaning of a device, a plug-in the profile names.

A register map is data (a TOML profile). What a device means over time -- a
command written into a block of registers and executed by another write, an
answer that only makes sense with what was written before -- is a *session*:
an object fed every pairing step of one server endpoint and unit, and the
clock. A profile names its session in its header (``session = "hrss"``); the
registry here maps that name to the class (or any factory) that makes one. The
annotator asks the registry (:func:`session_factory`), never a name it knows;
the live monitor asks each session for its panel (:meth:`Session.panel`).

Where a session comes from:

* the built-in ones, by a ``module:attribute`` path imported only when a
  profile in use names them (HRSS loads its command TOML then);
* :func:`register_session` at run time (a test, a program that embeds mbmon);
* an installed package's entry point in the group :data:`ENTRY_POINT_GROUP`
  (``mbmon.sessions``), looked up the first time a profile names a session
  that is not known otherwise.

A session implements :class:`Session`; subclassing it gives the optional
methods their defaults. ``docs/profiles.md`` ("A device with a session") shows
a whole one.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mbmon.model import Annotation, CommandUpdate, Stream, Transaction, fast_constructor

__all__ = [
    "ENTRY_POINT_GROUP",
    "CoreWatch",
    "Panel",
    "PanelRow",
    "Session",
    "SessionFactory",
    "UnknownSession",
    "annotation",
    "is_session",
    "register_session",
    "session_factory",
    "session_names",
    "unregister_session",
]

#: The entry-point group an installed package names its sessions in.
ENTRY_POINT_GROUP = "mbmon.sessions"

#: One row of a session's panel: ``(where, name, value, confirmed)`` --
#: ``("R203..R204", "A1", "90 deg", True)``; ``confirmed`` is false while the
#: write that put the value there is unanswered (the screen marks it).
PanelRow = tuple[str, str, str, bool]

_NOTHING = Annotation()
_new_annotation = fast_constructor(Annotation)


@dataclass(frozen=True, slots=True)
class Panel:
    """What a session shows in the live monitor's robot pane: a title and rows."""

    title: str
    rows: tuple[PanelRow, ...] = ()


@dataclass(frozen=True, slots=True)
class CoreWatch:
    """What a session must see of the steps the compiled core writes itself.

    The core (``mbmon/core/``) writes the lines of read requests and of their
    answers without a Python object per step; every other step (writes,
    exceptions, anything it does not decode) goes through the annotator and
    :meth:`Session.follow` as in the reference pipeline. A session that
    supports the core (:attr:`Session.core_ready`) says here which of the
    core's steps would change what it writes, and gets exactly those:

    * ``deadline``: from this capture time on, any step may say something by
      the clock alone (:meth:`Session.next_deadline`; ``inf``: never);
    * ``answers``: ``(fc, first, last, lo, hi)``: an answer to a read of
      function code ``fc`` that carries a register of ``first..last`` whose
      word, read as signed 16 bits, is outside ``lo..hi`` (``lo > hi``: any
      word) goes to :meth:`Session.core_answer`.

    The core asks again (:meth:`Session.core_watch`) after every call it
    makes into the session, so a watch only needs to be right until then.
    """

    deadline: float = math.inf
    answers: tuple[tuple[int, int, int, int, int], ...] = ()


class Session:
    """One device's state for one server endpoint and unit, fed pairing steps and ticks.

    The annotator makes one per (server endpoint, unit) whose profile names
    the session, as ``factory(stream, unit)``, and calls, in the hub's thread:

    * :meth:`follow` with every pairing step of that endpoint and unit (and the
      profile's notes for it): the step's one :class:`~mbmon.model.Annotation`
      (notes, command steps, state);
    * :meth:`tick` and :meth:`next_deadline`, so that something due by time
      alone is said on time while the line is silent;
    * :meth:`wants_read_request` before a read request (the step polling is
      made of): ``False`` lets the annotator answer it from its cache.

    The live monitor calls :meth:`panel` about four times a second.
    Only :meth:`follow` must be written; the rest have defaults here.

    The compiled core runs ``read --profile`` only for sessions with
    :attr:`core_ready` set, which implement :meth:`core_watch` and
    :meth:`core_answer` (see :class:`CoreWatch`); for the others it declines and
    the reference pipeline reads the input.
    """

    #: whether :meth:`core_watch` and :meth:`core_answer` are implemented exactly
    core_ready = False

    def __init__(self, stream: Stream, unit: int) -> None:
        self.stream = stream
        self.unit = unit

    def follow(self, tx: Transaction, notes: list[str]) -> Annotation:
        """The annotation of one pairing step: ``notes`` (the profile's, which the
        session may add to) plus the session's command steps and state."""
        return annotation(notes)

    def wants_read_request(self, ts: float) -> bool:
        """Whether :meth:`follow` must see a read request asked at ``ts`` (default: yes)."""
        return True

    def tick(self, now: float) -> list[CommandUpdate]:
        """Time ``now`` passed with no step: the command steps that makes due."""
        return []

    def next_deadline(self) -> float | None:
        """The earliest time :meth:`tick` reports something, or ``None``."""
        return None

    def panel(self) -> Panel | None:
        """What the live monitor shows of this session (``None``: nothing)."""
        return None

    def core_watch(self) -> CoreWatch:
        """Which of the compiled core's steps this session must see now (:class:`CoreWatch`)."""
        raise NotImplementedError(f"{type(self).__name__} does not support the compiled core")

    def core_answer(
        self, fc: int, address: int, values: tuple[int, ...], ts: float, stream: Stream
    ) -> tuple[list[str], list[CommandUpdate]]:
        """:meth:`follow` of an answered read that :meth:`core_watch` asked for, told in
        plain numbers: the request's function code and address, the answer's values (as
        many as asked), its time and stream. The session's own notes (the profile's come
        before them) and its command steps."""
        raise NotImplementedError(f"{type(self).__name__} does not support the compiled core")

    def core_write_answer(
        self, request: tuple[float, int, int, bytes], ts: float, stream: Stream
    ) -> tuple[list[str], list[CommandUpdate]] | None:
        """:meth:`follow` of the answer (not an exception) to a register write the core
        writes itself (FC 06, 10), told by its request's ``(time, stream id, transaction
        id, ADU)``: the session's notes and command steps, or ``None`` (the default) to
        have the step go through the annotator and :meth:`follow` instead."""
        return None


def annotation(
    notes: list[str], commands: tuple[CommandUpdate, ...] = (), state: Any = None
) -> Annotation:
    """The annotation of a step: the shared empty one when there is nothing to say."""
    if notes or commands or state is not None:
        return _new_annotation(tuple(notes), commands, state)  # type: ignore[no-any-return]
    return _NOTHING


#: What makes a session: a :class:`Session` subclass, or any callable of (stream, unit).
SessionFactory = Callable[[Stream, int], Session]


class UnknownSession(LookupError):
    """A profile names a session nobody registered."""


_BUILTIN: dict[str, str] = {"hrss": "mbmon.semantics.hrss.session:HrssSession"}
_registered: dict[str, SessionFactory | str] = dict(_BUILTIN)
_entry_points_read = False


def register_session(name: str, factory: SessionFactory | str) -> None:
    """Make ``session = "NAME"`` in a profile mean ``factory`` (a class, a callable of
    (stream, unit), or a ``"module:attribute"`` path imported when first used).
    Registering a name again replaces it."""
    if not name or not isinstance(name, str):
        raise ValueError(f"a session name is a non-empty string, got {name!r}")
    _registered[name] = factory


def unregister_session(name: str) -> None:
    """Forget a session :func:`register_session` added (a built-in one comes back)."""
    _registered.pop(name, None)
    if name in _BUILTIN:
        _registered[name] = _BUILTIN[name]


def is_session(name: str) -> bool:
    """Whether a profile may name ``name``: registered, or an installed plug-in's
    (installed packages are looked at only for a name not registered otherwise)."""
    if name in _registered:
        return True
    _read_entry_points()
    return name in _registered


def session_names() -> tuple[str, ...]:
    """Every session name a profile may use (installed plug-ins included), sorted."""
    _read_entry_points()
    return tuple(sorted(_registered))


def session_factory(name: str) -> SessionFactory:
    """What makes the session ``name``: imported now if it was registered as a path.

    Raises :class:`UnknownSession` for a name nothing registered, and for a
    path that does not import (the message says which and why).
    """
    found = _registered.get(name)
    if found is None:
        _read_entry_points()
        found = _registered.get(name)
    if found is None:
        raise UnknownSession(
            f"unknown session {name!r} (known: {', '.join(session_names()) or 'none'})"
        )
    if isinstance(found, str):
        found = _registered[name] = _import(name, found)
    return found


def _import(name: str, path: str) -> SessionFactory:
    module, _, attr = path.partition(":")
    try:
        obj = importlib.import_module(module)
        for part in attr.split(".") if attr else ():
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as e:
        raise UnknownSession(f"session {name!r}: cannot import {path!r}: {e}") from None
    if not callable(obj):
        raise UnknownSession(f"session {name!r}: {path!r} is not a class or a callable")
    return obj  # type: ignore[return-value]


def _read_entry_points() -> None:
    """Add the sessions installed packages name (group :data:`ENTRY_POINT_GROUP`), once;
    a name registered otherwise is kept. ``importlib.metadata`` is imported here, when a
    profile names a session nobody registered (it costs a run several milliseconds)."""
    from importlib import metadata

    global _entry_points_read
    if _entry_points_read:
        return
    _entry_points_read = True
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        _registered.setdefault(ep.name, ep.value)
