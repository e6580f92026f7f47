"""Profile notes: fields laid over the words or bits of a frame, as short texts.

``R201 = PTP (0)``, ``SI1 Start = ON``, ``A1 = 90.830°``, ``DI[1..8] = ON OFF …``,
``read A1..A6``: what :class:`~mbmon.semantics.annotate.Annotator` puts on a
frame. A :class:`Layout` (which fields sit over ``n`` registers at an address)
is decided once per profile, table, address and count and kept in the
profile's memo (bounded); the values are then formatted by
:mod:`mbmon.semantics.values`. :class:`SelectorMemory` keeps the group
selectors (``PR[n].type``) a frame does not carry itself.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import Any

from mbmon.semantics.profile import REGISTER_PREFIX, Field, FieldRef, Profile, Variant
from mbmon.semantics.profile.model import BIT_TABLES
from mbmon.semantics.values import format_value, raw_word, value_format, value_text
from mbmon.semantics.words import s16

__all__ = [
    "Layout",
    "SelectorMemory",
    "bit_notes",
    "field_notes",
    "layout_notes",
    "layout_of",
    "mask_note",
    "read_request_note",
    "remember",
    "selectable",
    "span_note",
]

_MAX_RUN_WORDS = 12  # values shown in a merged run / block note before "…"
_MAX_RUN_BITS = 8  # bits shown as ON/OFF words; longer runs list the ON ones


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
    if table in BIT_TABLES:
        return bit_notes(profile, table, start, values)
    return layout_notes(layout_of(profile, table, start, len(values)), table, start, values, verb,
                         selector)  # fmt: skip


def layout_notes(
    layout: Layout,
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
            notes.append(item[3] + format_value(item[4], values, a))
        elif kind is _RUN:
            notes.append(_run_note(item[3], values[a:b], item[4]))
        else:
            ref = item[3]
            notes.append(
                _register_note(ref, table, start + a, values[a:b], verb, start, values, selector)
            )
    return notes


@dataclass(frozen=True, slots=True)
class Layout:
    """What :func:`field_notes` shows for a number of registers at an address, value-free.

    ``selects``: an item reads a group selector (``PR[n].type``), which only
    then needs the selector memory.
    """

    items: tuple[tuple[Any, ...], ...]
    selects: bool


def layout_of(profile: Profile, table: str, start: int, n: int) -> Layout:
    """The layout of ``n`` registers of ``table`` at ``start`` (kept in the profile's memo)."""
    key = (_LAYOUT, table, start, n)
    memo = profile.memo
    layout = memo.get(key)
    if layout is None:
        items = _register_layout(profile, table, start, n)
        selects = any(item[0] is _FIELD and selectable(item[3]) for item in items)
        layout = Layout(items, selects)
        remember(memo, key, layout)
    return layout  # type: ignore[no-any-return]


def selectable(ref: FieldRef) -> bool:
    """Whether ``ref`` is read the way a group selector (``PR[n].type``) says."""
    entry = ref.entry
    return entry is not None and entry.select is not None and ref.base is not None


# Layout items: (_VALUE, a, b, "head = ", ValueFormat) | (_RUN, a, b, name, field)
# | (_FIELD, a, b, ref), where values[a:b] are the words the note shows.
_VALUE, _RUN, _FIELD = "value", "run", "field"
_LAYOUT, _READ_NOTE, _SPAN_NOTE = "layout", "read note", "span note"
_MEMO_MAX = 1024  # layouts and notes per profile: at most ~125 small tuples each, ~15 MB worst


def remember(memo: dict[Any, Any], key: Hashable, value: Any) -> None:
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
        if f.type != "block" and not selectable(ref) and hi - lo == f.words:
            head = _ref_text(ref, None) + " = "
            items.append((_VALUE, lo - start, hi - start, head, value_format(f, None)))
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
    return f"{head} = {value_text(f, variant, words)}"


def _partial_note(
    head: str, f: Field, ref: FieldRef, lo: int, words: Sequence[int], verb: str
) -> str:
    raw = " ".join(raw_word(f, w) for w in words)
    if f.words == 2:
        first_is_low = f.word_order == "low_high"
        have_first = lo == ref.address
        have, missing = ("low", "high") if have_first == first_is_low else ("high", "low")
        return f"{head} ({have} word) = {raw} ({missing} word not in this {verb})"
    off = lo - ref.address
    part = f"words {off + 1}..{off + len(words)} of {f.words}"
    return f"{head} ({part}) = {raw} (rest not in this {verb})"


def bit_notes(profile: Profile, table: str, start: int, bits: Sequence[int]) -> list[str]:
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


def read_request_note(
    profile: Profile, table: str, address: int | None, count: int | None
) -> tuple[str, ...]:
    if address is None or not count:
        return ()
    key = (_READ_NOTE, table, address, count)
    notes = profile.memo.get(key)
    if notes is None:
        names = _span_names(profile, table, address, min(count, 0x10000 - address))
        notes = (f"read {names}",) if names else ()
        remember(profile.memo, key, notes)
    return notes  # type: ignore[no-any-return]


def span_note(
    profile: Profile, table: str, address: int | None, count: int | None, verb: str
) -> list[str]:
    if address is None or not count:
        return []
    key = (_SPAN_NOTE, table, address, count, verb)
    note = profile.memo.get(key)
    if note is None:
        names = _span_names(profile, table, address, min(count, 0x10000 - address))
        note = f"{names} {verb}" if names else ""
        remember(profile.memo, key, note)
    return [note] if note else []


def mask_note(profile: Profile, address: int | None, fields: Any) -> list[str]:
    if address is None:
        return []
    ref = profile.lookup("holding_registers", address)
    and_mask, or_mask = fields.get("and_mask"), fields.get("or_mask")
    if ref is None or and_mask is None or or_mask is None:
        return []
    name = _one_name(ref, "holding_registers", address, address)
    head = _one_name(ref, "holding_registers", address, address, with_label=True)
    return [f"{head} = ({name} AND 0x{and_mask:04X}) OR 0x{or_mask:04X}"]
