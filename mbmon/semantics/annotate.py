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

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

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
from mbmon.semantics.profile import (
    REGISTER_PREFIX,
    Field,
    FieldRef,
    Profile,
    ProfileBinding,
    Variant,
)
from mbmon.semantics.session import Session, SessionFactory, session_factory
from mbmon.semantics.words import s16, u32_to_f32

__all__ = ["Annotator", "SelectorMemory", "annotator_for", "field_notes"]

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


_BITS = frozenset({"coils", "discrete_inputs"})
_MAX_RUN_WORDS = 12  # values shown in a merged run / block note before "…"
_MAX_RUN_BITS = 8  # bits shown as ON/OFF words; longer runs list the ON ones
_NO_UNIT_SPACE = frozenset({"°", "%", ""})


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
                notes = _layout_notes(layout, read.table, read.address, values, "read", selector)
            else:
                notes = self._read_notes(tx, pdu, frame, profile)
        else:
            notes = list(self._frame_notes(tx, frame, profile))
        if session is not None:
            return session.follow(tx, notes)
        return _new_annotation(tuple(notes), (), None) if notes else _EMPTY

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
        if table in _BITS:
            return _bit_notes(profile, table, start, values)
        layout = _layout(profile, table, start, len(values))
        selector = self._selector_reader(frame, profile, table) if layout.selects else None
        return _layout_notes(layout, table, start, values, verb, selector)

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
            return _read_request_note(profile, table, pdu.address, pdu.count)
        if pdu.kind is Kind.REQUEST:
            if shape == "write_single" or shape == "write_multiple":
                if pdu.address is None or not pdu.values:
                    return []
                return self._field_notes(frame, profile, table, pdu.address, pdu.values, "write")
            if shape == "mask_write":
                return _mask_note(profile, pdu.address, pdu.fields)
            if shape != "read_write":
                return []
            # read/write: write part now, read part with the response
            waddr = pdu.fields.get("write_address")
            wvals = pdu.fields.get("write_values")
            notes: list[str] = []
            if waddr is not None and wvals:
                notes += self._field_notes(frame, profile, table, waddr, wvals, "write")
            notes += _read_request_note(profile, table, pdu.address, pdu.count)
            return notes
        # responses
        if shape == "write_single":  # echo of the write: self-contained
            if pdu.address is None or not pdu.values:
                return []
            return self._field_notes(frame, profile, table, pdu.address, pdu.values, "write")
        if shape == "write_multiple":
            return _span_note(profile, table, pdu.address, pdu.count, "written")
        if shape == "mask_write":
            return _mask_note(profile, pdu.address, pdu.fields)
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


class SelectorMemory:
    """Last value of group selectors (PR[n].type) seen on one server, unit and table.

    Lets ``PR[2].Value1`` read as ``PR[2].X`` in a frame that does not carry
    ``PR[2].type`` itself.
    """

    __slots__ = ("_server", "_store", "_table", "_unit")

    def __init__(
        self, store: dict[tuple[str, int, str, int], int], server: str, unit: int, table: str
    ) -> None:
        self._store = store
        self._server = server
        self._unit = unit
        self._table = table

    def get(self, address: int) -> int | None:
        return self._store.get((self._server, self._unit, self._table, address))

    def put(self, address: int, value: int) -> None:
        self._store[(self._server, self._unit, self._table, address)] = value


# ---------------------------------------------------------------------- rendering


def field_notes(
    profile: Profile,
    table: str,
    start: int,
    values: Sequence[int],
    verb: str = "read",
    selector: SelectorMemory | None = None,
) -> list[str]:
    """One note per field (merged runs for plain repeated fields) for ``values`` at ``start``.

    ``verb`` ("read"/"write") words the mark on a half value.
    """
    if table in _BITS:
        return _bit_notes(profile, table, start, values)
    return _layout_notes(_layout(profile, table, start, len(values)), table, start, values, verb,
                         selector)  # fmt: skip


def _layout_notes(
    layout: _Layout,
    table: str,
    start: int,
    values: Sequence[int],
    verb: str,
    selector: SelectorMemory | None,
) -> list[str]:
    """:func:`field_notes` of register ``values`` at ``start`` that ``layout`` lays out."""
    notes: list[str] = []
    for item in layout.items:
        kind, a, b = item[0], item[1], item[2]
        if kind is _VALUE:  # one whole field that no selector re-reads: head fixed
            notes.append(item[3] + _format_value(item[4], values, a))
        elif kind is _RUN:
            notes.append(_run_note(item[3], values[a:b], item[4]))
        else:
            ref = item[3]
            notes.append(
                _register_note(ref, table, start + a, values[a:b], verb, start, values, selector)
            )
    return notes


@dataclass(frozen=True, slots=True)
class _Layout:
    """What :func:`field_notes` shows for a number of registers at an address, value-free.

    ``selects``: an item reads a group selector (``PR[n].type``), which only
    then needs the selector memory.
    """

    items: tuple[tuple[Any, ...], ...]
    selects: bool


def _layout(profile: Profile, table: str, start: int, n: int) -> _Layout:
    """The layout of ``n`` registers of ``table`` at ``start`` (kept in the profile's memo)."""
    key = (_LAYOUT, table, start, n)
    memo = profile.memo
    layout = memo.get(key)
    if layout is None:
        items = _register_layout(profile, table, start, n)
        selects = any(item[0] is _FIELD and _selectable(item[3]) for item in items)
        layout = _Layout(items, selects)
        _remember(memo, key, layout)
    return layout  # type: ignore[no-any-return]


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
    layout: _Layout | None


def _read_of(profile: Profile, pdu: Pdu) -> _Read:
    """The :class:`_Read` of a read request (FC 01..04), remembered by its PDU bytes."""
    table = _TABLE[pdu.fc]
    address, count = pdu.address, pdu.count
    found = _read_request_note(profile, table, address, count)
    layout = None
    # layouts are made ahead for reads within the spec's quantity limit only
    limit = FUNCTIONS[pdu.fc].max_count or 0
    if table not in _BITS and address is not None and count and count <= limit:
        layout = _layout(profile, table, address, count)
    read = _Read(
        _new_annotation(found, (), None) if found else _EMPTY,
        table,
        address if address is not None else 0,
        count,
        layout,
    )
    _remember(profile.memo, pdu.raw, read)
    return read


def _selectable(ref: FieldRef) -> bool:
    """Whether ``ref`` is read the way a group selector (``PR[n].type``) says."""
    entry = ref.entry
    return entry is not None and entry.select is not None and ref.base is not None


# Layout items: (_VALUE, a, b, "head = ", _ValueFormat) | (_RUN, a, b, name, field)
# | (_FIELD, a, b, ref), where values[a:b] are the words the note shows.
_VALUE, _RUN, _FIELD = "value", "run", "field"
_LAYOUT, _READ_NOTE, _SPAN_NOTE = "layout", "read note", "span note"
_MEMO_MAX = 1024  # layouts and notes per profile: at most ~125 small tuples each, ~15 MB worst


def _remember(memo: dict[Any, Any], key: Hashable, value: Any) -> None:
    """Keep ``value`` for ``key`` in a profile's memo; the memo is emptied when full."""
    if len(memo) >= _MEMO_MAX:
        memo.clear()
    memo[key] = value


def _register_layout(
    profile: Profile, table: str, start: int, n: int
) -> tuple[tuple[Any, ...], ...]:
    """What :func:`field_notes` shows for ``n`` registers at ``start``: the value-free part."""
    items: list[tuple[Any, ...]] = []
    end = start + n
    i = 0
    lookup = profile.lookup
    while i < n:
        ref = lookup(table, start + i)
        if ref is None:
            i += 1
            continue
        f = ref.field
        lo = max(ref.address, start)
        hi = min(ref.address + f.words, end)
        if _plain(ref):
            j = hi - start
            run = [ref]
            while j < n:
                nxt = lookup(table, start + j)
                if nxt is None or nxt.entry is not ref.entry or not _plain(nxt):
                    break
                run.append(nxt)
                j += 1
            if len(run) > 1:
                items.append((_RUN, i, j, _run_name(run), f))
                i = j
                continue
        if f.type != "block" and not _selectable(ref) and hi - lo == f.words:
            head = _ref_text(ref, None) + " = "
            items.append((_VALUE, lo - start, hi - start, head, _value_format(f, None)))
        else:
            items.append((_FIELD, lo - start, hi - start, ref))
        i = hi - start
    return tuple(items)


def _plain(ref: FieldRef) -> bool:
    """A repeated one-word field with nothing to say but its number (SRR[n])."""
    f = ref.field
    return (
        ref.entry is not None
        and not ref.entry.fields
        and f.words == 1
        and f.type in ("u16", "s16")
        and f.enum is None
        and f.scale is None
        and f.unit is None
        and f.display == "dec"
        and not (f.labels and ref.n in f.labels)
        and f.label is None
    )


def _run_note(name: str, values: Sequence[int], f: Field) -> str:
    shown = [str(s16(v) if f.type == "s16" else v) for v in values[:_MAX_RUN_WORDS]]
    if len(values) > _MAX_RUN_WORDS:
        shown.append(f"… (+{len(values) - _MAX_RUN_WORDS})")
    return f"{name} = {' '.join(shown)}"


def _run_name(run: list[FieldRef]) -> str:
    first, last = run[0], run[-1]
    entry = first.entry
    if entry is not None and entry.name.endswith("[{n}]"):
        return entry.name.replace("{n}", f"{first.n}..{last.n}")
    return f"{first.name}..{last.name}"


def _ref_text(ref: FieldRef, variant: Variant | None) -> str:
    name = ref.name
    label = ref.label
    if variant is not None:
        if variant.name is not None:
            parent = ref.entry.element_name(ref.n) if ref.entry is not None else ""
            name = f"{parent}.{variant.name}" if parent else variant.name
        if variant.label is not None:
            label = variant.label
    return f"{name} {label}" if label else name


def _register_note(
    ref: FieldRef,
    table: str,
    lo: int,
    words: Sequence[int],
    verb: str,
    start: int,
    values: Sequence[int],
    selector: SelectorMemory | None,
) -> str:
    f = ref.field
    if f.type == "block":
        prefix = REGISTER_PREFIX.get(table, "")
        hi = lo + len(words) - 1
        span = f"{prefix}{lo}" if hi == lo else f"{prefix}{lo}..{prefix}{hi}"
        label = f.label or f.name
        shown = [str(s16(v)) for v in words[:_MAX_RUN_WORDS]]
        if len(words) > _MAX_RUN_WORDS:
            shown.append(f"… (+{len(words) - _MAX_RUN_WORDS})")
        return f"{span} {label} = {' '.join(shown)}"
    variant = None
    entry = ref.entry
    if entry is not None and entry.select is not None and ref.base is not None:
        sel = next(x for x in entry.fields if x.name == entry.select)
        sel_addr = ref.base + sel.address
        sel_value: int | None
        if start <= sel_addr < start + len(values):
            sel_value = s16(values[sel_addr - start])
            if selector is not None:
                selector.put(sel_addr, sel_value)
        else:
            sel_value = selector.get(sel_addr) if selector is not None else None
        if sel_value is not None and f.variants:
            variant = f.variants.get(sel_value)
    head = _ref_text(ref, variant)
    if len(words) < f.words:
        return _partial_note(head, f, ref, lo, words, verb)
    return f"{head} = {_value_text(f, variant, words)}"


def _partial_note(
    head: str, f: Field, ref: FieldRef, lo: int, words: Sequence[int], verb: str
) -> str:
    raw = " ".join(_raw_word(f, w) for w in words)
    if f.words == 2:
        first_is_low = f.word_order == "low_high"
        have_first = lo == ref.address
        have, missing = ("low", "high") if have_first == first_is_low else ("high", "low")
        return f"{head} ({have} word) = {raw} ({missing} word not in this {verb})"
    off = lo - ref.address
    part = f"words {off + 1}..{off + len(words)} of {f.words}"
    return f"{head} ({part}) = {raw} (rest not in this {verb})"


def _raw_word(f: Field, w: int) -> str:
    if f.display == "hex":
        return f"0x{w & 0xFFFF:04X}"
    return str(w & 0xFFFF if f.type in ("u16", "u32", "version") else s16(w))


def _value_text(f: Field, variant: Variant | None, words: Sequence[int]) -> str:
    """The value of field ``f`` (read as ``variant`` says, if any) in its complete ``words``."""
    return _format_value(_value_format(f, variant), words, 0)


@dataclass(frozen=True, slots=True)
class _ValueFormat:
    """How a field's words become text, decided once per field and variant (value-free)."""

    type: str
    words: int
    high_low: bool  # word order of two-register types
    template: str  # "version": the format string
    enum: Mapping[int, str] | None
    enum_by_value: bool  # enum_style "value": "1 (execute)"
    hex: bool
    scale: float  # f32: the factor; integers: used when ``spec`` is set
    spec: str | None  # format spec of a scaled integer (".3f"); None: the integer as is
    suffix: str  # the unit as written after the number ("°", " mm", "")
    range: tuple[int, int] | None
    #: a scale of exactly 10**-k with ``spec`` ".kf": (10**k, a %-template of sign,
    #: whole part, k-digit fraction, unit), so the text is made from the integer's
    #: digits (what ``format(raw * scale, spec)`` gives, cheaper)
    decimal: tuple[int, str] | None = None


def _value_format(f: Field, variant: Variant | None) -> _ValueFormat:
    scale, unit = f.scale, f.unit
    if f.type == "f32":
        if variant is not None and variant.scale is not None:
            scale = variant.scale
        if variant is not None and variant.unit:
            unit = variant.unit
        spec = None
    else:
        if variant is not None:
            if variant.scale is not None:
                scale = variant.scale
            if variant.unit is not None:
                unit = variant.unit
        spec = None if scale is None or scale == 1 else f".{_decimals(scale)}f"
    return _ValueFormat(
        type=f.type,
        words=f.words,
        high_low=f.word_order != "low_high",
        template=f.format or "",
        enum=f.enum,
        enum_by_value=f.enum_style == "value",
        hex=f.display == "hex",
        scale=1.0 if scale is None else scale,
        spec=spec,
        suffix="" if not unit else unit if unit in _NO_UNIT_SPACE else f" {unit}",
        range=f.range,
        decimal=_decimal_point(scale, spec),
    )


def _decimal_point(scale: float | None, spec: str | None) -> tuple[int, str] | None:
    """``(10**k, template)`` when ``scale`` is exactly 10**-k (0.1, 0.01, 0.001, ...)
    and ``spec`` is ".kf": then ``format(raw * scale, spec)`` is the integer ``raw``
    with a decimal point k digits from its end (the float's error is far below half
    a last digit)."""
    if scale is None or spec is None:
        return None
    k = _decimals(scale)
    if k < 1 or spec != f".{k}f" or repr(scale) != repr(10.0**-k):
        return None
    return 10**k, f"%s%d.%0{k}d%s"


def _format_value(v: _ValueFormat, values: Sequence[int], i: int) -> str:
    """The text of the value whose ``v.words`` words start at ``values[i]``."""
    t = v.type
    if t == "version":
        return v.template.format(*(w & 0xFFFF for w in values[i : i + v.words]))
    if t == "u16":
        raw = values[i] & 0xFFFF
    elif t == "s16":
        raw = values[i] & 0xFFFF
        if raw & 0x8000:
            raw -= 0x10000
    else:
        low, high = (values[i + 1], values[i]) if v.high_low else (values[i], values[i + 1])
        u = ((high & 0xFFFF) << 16) | (low & 0xFFFF)
        if t == "f32":
            return f"{u32_to_f32(u) * v.scale:g}{v.suffix}"
        raw = u - 0x100000000 if t == "i32" and u & 0x80000000 else u
    enum = v.enum
    if enum is not None:
        name = enum.get(raw)
        if name is None:
            text = f"{raw} (unknown)"
        elif v.enum_by_value:
            text = f"{raw} ({name})"
        else:
            text = f"{name} ({raw})"
    elif v.hex:
        text = f"0x{raw & 0xFFFFFFFF:0{4 * v.words}X}"
    elif v.spec is None:
        text = f"{raw}{v.suffix}"
    elif v.decimal is not None:
        divisor, template = v.decimal
        whole, frac = divmod(-raw if raw < 0 else raw, divisor)
        text = template % ("-" if raw < 0 else "", whole, frac, v.suffix)
    else:
        text = format(raw * v.scale, v.spec) + v.suffix
    rng = v.range
    if rng is not None and not rng[0] <= raw <= rng[1]:
        text += f" (out of range {rng[0]}..{rng[1]})"
    return text


_DECIMALS: dict[float, int] = {}


def _decimals(scale: float) -> int:
    """As many decimals as the scale has: 0.001 -> 3, 0.25 -> 2, 10 -> 0."""
    decimals = _DECIMALS.get(scale)
    if decimals is None:
        exp = Decimal(repr(scale)).normalize().as_tuple().exponent
        decimals = _DECIMALS[scale] = min(-exp, 9) if isinstance(exp, int) and exp < 0 else 0
    return decimals


def _bit_notes(profile: Profile, table: str, start: int, bits: Sequence[int]) -> list[str]:
    notes: list[str] = []
    n = len(bits)
    i = 0
    lookup = profile.lookup
    while i < n:
        ref = lookup(table, start + i)
        if ref is None:
            i += 1
            continue
        if ref.label is None and ref.entry is not None:
            j = i + 1
            while j < n:
                nxt = lookup(table, start + j)
                if nxt is None or nxt.entry is not ref.entry or nxt.label is not None:
                    break
                j += 1
            if j - i > 1:
                run = [lookup(table, start + k) for k in range(i, j)]
                notes.append(_bit_run_note(run, bits[i:j]))  # type: ignore[arg-type]
                i = j
                continue
        head = f"{ref.name} {ref.label}" if ref.label else ref.name
        notes.append(f"{head} = {'ON' if bits[i] else 'OFF'}")
        i += 1
    return notes


def _bit_run_note(run: list[FieldRef], bits: Sequence[int]) -> str:
    name = _run_name(run)
    if len(bits) <= _MAX_RUN_BITS:
        return f"{name} = {' '.join('ON' if b else 'OFF' for b in bits)}"
    on = [r.name for r, b in zip(run, bits, strict=True) if b]
    if not on:
        return f"{name} = all OFF"
    if len(on) == len(bits):
        return f"{name} = all ON"
    listed = ", ".join(on[:_MAX_RUN_BITS])
    if len(on) > _MAX_RUN_BITS:
        listed += f", … (+{len(on) - _MAX_RUN_BITS})"
    return f"{name} = {len(on)} ON ({listed})"


def _span_names(profile: Profile, table: str, address: int, count: int) -> str | None:
    """Field names from ``address`` over ``count`` addresses: ``A1..A6``, ``DI[1..8]``."""
    first = last = None
    first_a = last_a = 0
    lookup = profile.lookup
    for a in range(address, address + count):
        ref = lookup(table, a)
        if ref is None:
            continue
        if first is None:
            first, first_a = ref, a
        last, last_a = ref, a
    if first is None or last is None:
        return None
    if first.field is last.field and first.address == last.address:
        return _one_name(first, table, first_a, last_a, with_label=True)
    if first.entry is not None and first.entry is last.entry and not first.entry.fields:
        return _run_name([first, last])
    return f"{_one_name(first, table, first_a, first_a)}..{_one_name(last, table, last_a, last_a)}"


def _one_name(ref: FieldRef, table: str, lo: int, hi: int, *, with_label: bool = False) -> str:
    if ref.field.type == "block":
        p = REGISTER_PREFIX.get(table, "")
        span = f"{p}{lo}" if lo == hi else f"{p}{lo}..{p}{hi}"
        return f"{span} {ref.field.label}" if with_label and ref.field.label else span
    if with_label and ref.label:
        return f"{ref.name} {ref.label}"
    return ref.name


def _read_request_note(
    profile: Profile, table: str, address: int | None, count: int | None
) -> tuple[str, ...]:
    if address is None or not count:
        return ()
    key = (_READ_NOTE, table, address, count)
    notes = profile.memo.get(key)
    if notes is None:
        names = _span_names(profile, table, address, min(count, 0x10000 - address))
        notes = (f"read {names}",) if names else ()
        _remember(profile.memo, key, notes)
    return notes  # type: ignore[no-any-return]


def _span_note(
    profile: Profile, table: str, address: int | None, count: int | None, verb: str
) -> list[str]:
    if address is None or not count:
        return []
    key = (_SPAN_NOTE, table, address, count, verb)
    note = profile.memo.get(key)
    if note is None:
        names = _span_names(profile, table, address, min(count, 0x10000 - address))
        note = f"{names} {verb}" if names else ""
        _remember(profile.memo, key, note)
    return [note] if note else []


def _mask_note(profile: Profile, address: int | None, fields: Any) -> list[str]:
    if address is None:
        return []
    ref = profile.lookup("holding_registers", address)
    and_mask, or_mask = fields.get("and_mask"), fields.get("or_mask")
    if ref is None or and_mask is None or or_mask is None:
        return []
    name = _one_name(ref, "holding_registers", address, address)
    head = _one_name(ref, "holding_registers", address, address, with_label=True)
    return [f"{head} = ({name} AND 0x{and_mask:04X}) OR 0x{or_mask:04X}"]


def annotator_for(specs: Sequence[str]) -> Annotator | None:
    """The annotator for ``--profile`` values, or ``None`` when none is given.

    Raises :class:`~mbmon.semantics.profile.ProfileError` for a spec that does not
    load or bind; the message names the file, line and key.
    """
    if not specs:
        return None
    return Annotator(ProfileBinding.parse(specs))
