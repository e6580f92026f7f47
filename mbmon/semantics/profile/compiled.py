"""A profile's register map in the flat form the compiled core reads.

The annotator (:mod:`mbmon.semantics.annotate`) lays a profile's fields over a
frame's words with :func:`~mbmon.semantics.notes.layout_of` and formats each
value with :func:`~mbmon.semantics.values.format_value`. For a read request
(function code, address, count) this module turns the same layout, decided
once, into :class:`CompiledRead`: the request's notes as texts and, for the
answers, a tuple of flat operations -- word offsets, a number type, a format
code and the texts around the number -- that ``mbmon/core/_reader.pyx``
executes on the answer's words, writing the very notes the annotator writes.

What it does not compile (a layout item whose words a group selector re-reads,
a block, a value cut by the read, a ``version`` field, bits) leaves
``answer`` ``None``: the core then hands that answer to the annotator itself.
Nothing here decides what a note says; it only re-expresses the layout.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from mbmon.protocol.functions import FUNCTIONS, PROFILE_TABLE, SHAPE
from mbmon.semantics.notes import (
    _MAX_RUN_WORDS,
    _RUN,
    _VALUE,
    layout_of,
    read_request_note,
    span_note,
)
from mbmon.semantics.profile.model import BIT_TABLES, Profile
from mbmon.semantics.values import ValueFormat

__all__ = [
    "F_DECIMAL",
    "F_ENUM_NAME",
    "F_ENUM_VALUE",
    "F_FLOAT",
    "F_HEX",
    "F_PLAIN",
    "F_SCALED",
    "OP_RUN",
    "OP_VALUE",
    "TYPES",
    "CompiledRead",
    "compile_read",
    "compile_write_answer",
]

#: operation kinds: one value (``head`` number ``suffix``), or a run of plain words
OP_VALUE, OP_RUN = 0, 1
#: number types, as the core reads the words
TYPES: Mapping[str, int] = {"u16": 0, "s16": 1, "u32": 2, "i32": 3, "f32": 4}
#: how the number is written (:func:`~mbmon.semantics.values.format_value`'s branches)
F_PLAIN, F_HEX, F_DECIMAL, F_SCALED, F_ENUM_NAME, F_ENUM_VALUE, F_FLOAT = range(7)

#: one operation: (kind, first word, end word, type, high word first, format,
#: decimals, divisor, scale, range or None, head text, suffix text, enum or None)
Op = tuple[Any, ...]


@dataclass(frozen=True, slots=True)
class CompiledRead:
    """What the core needs for one read request shape of one profile.

    ``request``: the notes of the request's step; ``answer``: the operations
    that write the notes of an answer carrying all ``count`` values, or ``None``
    when the annotator must write them.
    """

    request: tuple[str, ...]
    answer: tuple[Op, ...] | None


def compile_read(profile: Profile, fc: int, address: int, count: int) -> CompiledRead:
    """The :class:`CompiledRead` of a well-formed read request (FC 01..04 or a code of
    that shape) for ``profile``."""
    row = FUNCTIONS.get(fc)
    table = PROFILE_TABLE[row.table] if row is not None and row.table is not None else None
    if table is None:
        return CompiledRead((), None)
    request = read_request_note(profile, table, address, count)
    limit = row.max_count or 0 if row is not None else 0
    if table in BIT_TABLES or not count or count > limit:
        return CompiledRead(request, None)
    return CompiledRead(request, _compile_layout(layout_of(profile, table, address, count).items))


def compile_write_answer(profile: Profile, fc: int, address: int, count: int) -> CompiledRead:
    """The :class:`CompiledRead` of the answer to a well-formed register write (the
    annotator's notes of that answer): a single write's echo is laid out like one
    register read (``answer``), a multiple write's answer is the span it wrote
    (``request``, e.g. ``R201..R221 written``). ``answer`` ``None``: not compiled."""
    row = FUNCTIONS.get(fc)
    table = PROFILE_TABLE[row.table] if row is not None and row.table is not None else None
    shape = SHAPE.get(fc)
    if table is None or table in BIT_TABLES:
        return CompiledRead((), None)
    if shape == "write_single":
        return CompiledRead((), _compile_layout(layout_of(profile, table, address, 1).items))
    if shape == "write_multiple":
        return CompiledRead(tuple(span_note(profile, table, address, count, "written")), ())
    return CompiledRead((), None)


def _compile_layout(items: tuple[tuple[Any, ...], ...]) -> tuple[Op, ...] | None:
    ops: list[Op] = []
    for item in items:
        kind = item[0]
        if kind is _VALUE:
            op = _value_op(item[1], item[2], item[3], item[4])
            if op is None:
                return None
            ops.append(op)
        elif kind is _RUN:
            f = item[4]
            signed = f.type == "s16"
            ops.append(
                (OP_RUN, item[1], item[2], TYPES["s16" if signed else "u16"], False, F_PLAIN,
                 _MAX_RUN_WORDS, 0, 1.0, None, f"{item[3]} = ", "", None)
            )  # fmt: skip
        else:  # a field a selector re-reads, a block or a value the read cuts
            return None
    return tuple(ops)


def _value_op(a: int, b: int, head: str, v: ValueFormat) -> Op | None:
    """One whole value's operation, or ``None`` for a format the core does not write."""
    t = TYPES.get(v.type)
    if t is None or b - a != v.words or v.words != (2 if v.type in ("u32", "i32", "f32") else 1):
        return None
    if v.type == "f32":
        return (OP_VALUE, a, b, t, v.high_low, F_FLOAT, 0, 0, v.scale, None, head, v.suffix, None)
    decimals, divisor = 0, 0
    enum: dict[int, str] | None = None
    if v.enum is not None:
        fmt = F_ENUM_VALUE if v.enum_by_value else F_ENUM_NAME
        enum = {int(k): str(name) for k, name in v.enum.items()}
    elif v.hex:
        fmt = F_HEX
    elif v.spec is None:
        fmt = F_PLAIN
    elif v.decimal is not None:
        fmt = F_DECIMAL
        divisor = v.decimal[0]
        decimals = len(str(divisor)) - 1
    else:
        if not (v.spec.startswith(".") and v.spec.endswith("f") and v.spec[1:-1].isdigit()):
            return None
        fmt = F_SCALED
        decimals = int(v.spec[1:-1])
    return (OP_VALUE, a, b, t, v.high_low, fmt, decimals, divisor, v.scale, v.range, head,
            v.suffix, enum)  # fmt: skip
