"""The annotator: device-profile notes for every pairing step.

For each :class:`~mbmon.model.Transaction` the pipeline hands over, the
annotator finds the profile bound to the server endpoint and unit, and turns the
values of the frame the step reports (the request while it is pending, the
response once answered) into compact notes, one per field:
``R201 = PTP (0)``, ``SI1 Start = ON``, ``A1 = 90.830°``, ``PR[2].X = 90.000 mm``.
Responses to reads take their addresses from the paired request. A value that
spans two registers is combined only when both words are in the same frame;
otherwise the half is shown raw and marked.

When the profile names a device session (``session = "hrss"``), the annotator
keeps one per (server endpoint, unit), made by what the session registry
(:mod:`mbmon.semantics.session`) gives for that name, and merges its notes,
command steps and state into the result.

Cost: with no profile bound, :meth:`Annotator.annotate` returns a shared empty
annotation at once; with a profile, each field is one dict look-up.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from mbmon.model import (
    Annotation,
    CommandUpdate,
    Frame,
    Kind,
    Pdu,
    Stream,
    Transaction,
    TxStatus,
    fast_constructor,
)
from mbmon.protocol.functions import FUNCTIONS, PROFILE_TABLE, SHAPE, derived
from mbmon.semantics.notes import (
    Layout,
    SelectorMemory,
    bit_notes,
    layout_notes,
    layout_of,
    mask_note,
    read_request_note,
    remember,
    span_note,
)
from mbmon.semantics.profile import Profile, ProfileBinding
from mbmon.semantics.profile.model import BIT_TABLES
from mbmon.semantics.session import Session, SessionFactory, session_factory

__all__ = ["Annotator", "annotator_for"]

_EMPTY = Annotation()
_new_annotation = fast_constructor(Annotation)  # per step: twice as fast as the class
_PENDING, _TIMEOUT, _ANSWERED = TxStatus.PENDING, TxStatus.TIMEOUT, TxStatus.ANSWERED
_REQUEST, _RESPONSE = Kind.REQUEST, Kind.RESPONSE
#: the reads (shape "read") and function code -> profile table, from the one
#: function-code table (kept up to date by :func:`_from_table`)
_READ_FCS: set[int] = set()
_TABLE: dict[int, str] = {}


@derived
def _from_table() -> None:
    _READ_FCS.clear()
    _READ_FCS.update(code for code, shape in SHAPE.items() if shape == "read")
    _TABLE.clear()
    _TABLE.update(
        {code: PROFILE_TABLE[f.table] for code, f in FUNCTIONS.items() if f.table is not None}
    )


class Annotator:
    """Turns pairing steps into profile notes; owns the device sessions and selector memory."""

    def __init__(self, binding: ProfileBinding | None = None) -> None:
        self._binding = binding if binding is not None else ProfileBinding()
        self._off = self._binding.empty
        self._sessions: dict[tuple[str, int], Session] = {}
        self._factories: dict[str, SessionFactory] = {}  # by session name, asked once each
        # last value of group selectors (PR[n].type) per (server, unit, table, address)
        self._selectors: dict[tuple[str, int, str, int], int] = {}
        self._memories: dict[tuple[str, int, str], SelectorMemory] = {}  # views of _selectors
        # the (stream, unit) of the last step, its profile and session (see _bind)
        self._last_stream: Stream | None = None
        self._last_unit = -1
        self._last_profile: Profile | None = None
        self._last_session: Session | None = None

    @property
    def binding(self) -> ProfileBinding:
        return self._binding

    @property
    def has_sessions(self) -> bool:
        """Whether a bound profile names a device session (the monitor's robot pane)."""
        return any(p.session is not None for p in self._binding.profiles())

    def sessions(self) -> dict[tuple[str, int], Session]:
        """The device sessions by (server endpoint, unit), for listeners that show them."""
        return dict(self._sessions)

    def annotate(self, tx: Transaction) -> Annotation:
        """Notes, command steps and state for one pairing step."""
        if self._off:
            return _EMPTY
        status = tx.status
        frame = tx.request if status is _PENDING or status is _TIMEOUT else tx.response
        if frame is None:
            return _EMPTY
        stream, unit = frame.stream, frame.unit
        if stream is self._last_stream and unit == self._last_unit:
            profile, session = self._last_profile, self._last_session
        else:
            profile, session = self._bind(stream, unit)
        if profile is None:
            return _EMPTY
        pdu = frame.pdu
        if status is _PENDING and pdu.kind is _REQUEST and pdu.fc in _READ_FCS:
            # the most common step of all (a poll asked for): its annotation is cached
            read = profile.memo.get(pdu.raw)
            if read is None:
                read = _read_of(profile, pdu)
            if session is None or not session.wants_read_request(tx.ts):
                return read.asked
            return session.follow(tx, list(read.asked.notes))
        if status is _TIMEOUT:
            notes: list[str] = []
        elif status is _ANSWERED and pdu.kind is _RESPONSE and pdu.fc in _READ_FCS:
            # the other half of polling: the answer, laid out as its request's bytes say
            asked = tx.request
            values = pdu.values
            read = None
            if asked is not None and asked.pdu.fc == pdu.fc and values is not None:
                read = profile.memo.get(asked.pdu.raw)
            if (
                read is not None
                and read.layout is not None
                and values is not None
                and len(values) == read.count
            ):
                layout = read.layout
                selector = None
                if layout.selects:
                    selector = self._selector_reader(frame, profile, read.table)
                notes = layout_notes(layout, read.table, read.address, values, "read", selector)
            else:
                notes = self._read_notes(tx, pdu, frame, profile)
        else:
            notes = list(self._frame_notes(tx, frame, profile))
        if session is not None:
            return session.follow(tx, notes)
        return _new_annotation(tuple(notes), (), None) if notes else _EMPTY

    def bound(self, stream: Stream, unit: int) -> tuple[Profile | None, Session | None]:
        """The profile bound to a stream's server and ``unit`` and its device session
        (made now if it is the first step there), or ``None`` for either: what the
        compiled core asks once per stream and unit."""
        return self._bind(stream, unit)

    def _bind(self, stream: Stream, unit: int) -> tuple[Profile | None, Session | None]:
        """The profile and session (or ``None``) of a stream and unit, remembered as the
        last ones: consecutive steps mostly share a stream, and a binding never changes."""
        profile = self._binding.for_(stream, unit)
        session = None
        if profile is not None and profile.session is not None:
            session = self._session(stream, unit, profile.session)
        self._last_stream, self._last_unit = stream, unit
        self._last_profile, self._last_session = profile, session
        return profile, session

    def tick(self, now: float) -> list[CommandUpdate]:
        """Time ``now`` passed: command steps the sessions make due (never-completed warnings).

        The pipeline emits each as a COMMAND record; nothing here needs a frame.
        """
        out: list[CommandUpdate] = []
        for session in self._sessions.values():
            out += session.tick(now)
        return out

    def next_deadline(self) -> float | None:
        """The earliest time a :meth:`tick` reports something, or ``None``."""
        deadline: float | None = None
        for session in self._sessions.values():
            d = session.next_deadline()
            if d is not None and (deadline is None or d < deadline):
                deadline = d
        return deadline

    # ------------------------------------------------------------------ sessions

    def _session(self, stream: Stream, unit: int, name: str) -> Session:
        """The session ``name`` of a server endpoint and unit, made on first use."""
        key = (stream.server, unit)
        session = self._sessions.get(key)
        if session is None:
            factory = self._factories.get(name)
            if factory is None:  # the registry imports a built-in session only now
                factory = self._factories[name] = session_factory(name)
            session = self._sessions[key] = factory(stream, unit)
        return session

    # ------------------------------------------------------------------ notes

    def _read_notes(self, tx: Transaction, pdu: Pdu, frame: Frame, profile: Profile) -> list[str]:
        """:meth:`_frame_notes` of the answer to a read (FC 01..04), what polling is made of."""
        req = tx.request
        values = pdu.values
        if req is None or req.pdu.address is None or not values:
            return []
        start, count = req.pdu.address, req.pdu.count
        if count is not None and len(values) > count:
            values = values[:count]
        return self._field_notes(frame, profile, _TABLE[pdu.fc], start, values, "read")

    def _field_notes(
        self,
        frame: Frame,
        profile: Profile,
        table: str,
        start: int,
        values: Sequence[int],
        verb: str,
    ) -> list[str]:
        """:func:`field_notes` with the selector memory of the frame's server and unit."""
        if table in BIT_TABLES:
            return bit_notes(profile, table, start, values)
        layout = layout_of(profile, table, start, len(values))
        selector = self._selector_reader(frame, profile, table) if layout.selects else None
        return layout_notes(layout, table, start, values, verb, selector)

    def _frame_notes(self, tx: Transaction, frame: Frame, profile: Profile) -> Sequence[str]:
        pdu = frame.pdu
        if pdu.kind is Kind.EXCEPTION:
            return ()
        fc = pdu.fc
        table = _TABLE.get(fc)
        if table is None:
            return ()
        shape = SHAPE.get(fc)
        if pdu.kind is Kind.REQUEST and shape == "read":
            return read_request_note(profile, table, pdu.address, pdu.count)
        if pdu.kind is Kind.REQUEST:
            if shape == "write_single" or shape == "write_multiple":
                if pdu.address is None or not pdu.values:
                    return []
                return self._field_notes(frame, profile, table, pdu.address, pdu.values, "write")
            if shape == "mask_write":
                return mask_note(profile, pdu.address, pdu.fields)
            if shape != "read_write":
                return []
            # read/write: write part now, read part with the response
            waddr = pdu.fields.get("write_address")
            wvals = pdu.fields.get("write_values")
            notes: list[str] = []
            if waddr is not None and wvals:
                notes += self._field_notes(frame, profile, table, waddr, wvals, "write")
            notes += read_request_note(profile, table, pdu.address, pdu.count)
            return notes
        # responses
        if shape == "write_single":  # echo of the write: self-contained
            if pdu.address is None or not pdu.values:
                return []
            return self._field_notes(frame, profile, table, pdu.address, pdu.values, "write")
        if shape == "write_multiple":
            return span_note(profile, table, pdu.address, pdu.count, "written")
        if shape == "mask_write":
            return mask_note(profile, pdu.address, pdu.fields)
        if shape != "read" and shape != "read_write":
            return []
        req = tx.request
        if req is None or req.pdu.address is None or not pdu.values:
            return []
        values: Sequence[int] = pdu.values
        if req.pdu.count is not None and len(values) > req.pdu.count:
            values = values[: req.pdu.count]
        return self._field_notes(frame, profile, table, req.pdu.address, values, "read")

    def _selector_reader(self, frame: Frame, profile: Profile, table: str) -> SelectorMemory:
        key = (frame.stream.server, frame.unit, table)
        memory = self._memories.get(key)
        if memory is None:
            if len(self._memories) >= 4096:  # one per server, unit and table: bounded all the same
                self._memories.clear()
            memory = self._memories[key] = SelectorMemory(self._selectors, *key)
        return memory


@dataclass(frozen=True, slots=True)
class _Read:
    """What a read request's PDU bytes mean, kept in the profile's memo by those bytes.

    ``asked``: the annotation of the step that asks; ``layout``: that of a register
    answer with all ``count`` values asked for (``None`` for bits, or when the
    request has no address or count).
    """

    asked: Annotation
    table: str
    address: int
    count: int | None
    layout: Layout | None


def _read_of(profile: Profile, pdu: Pdu) -> _Read:
    """The :class:`_Read` of a read request (FC 01..04), remembered by its PDU bytes."""
    table = _TABLE[pdu.fc]
    address, count = pdu.address, pdu.count
    found = read_request_note(profile, table, address, count)
    layout = None
    # layouts are made ahead for reads within the spec's quantity limit only
    limit = FUNCTIONS[pdu.fc].max_count or 0
    if table not in BIT_TABLES and address is not None and count and count <= limit:
        layout = layout_of(profile, table, address, count)
    read = _Read(
        _new_annotation(found, (), None) if found else _EMPTY,
        table,
        address if address is not None else 0,
        count,
        layout,
    )
    remember(profile.memo, pdu.raw, read)
    return read


def annotator_for(specs: Sequence[str]) -> Annotator | None:
    """The annotator for ``--profile`` values, or ``None`` when none is given.

    Raises :class:`~mbmon.semantics.profile.ProfileError` for a spec that does not
    load or bind; the message names the file, line and key.
    """
    if not specs:
        return None
    return Annotator(ProfileBinding.parse(specs))
