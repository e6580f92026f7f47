"""Field values as text: how a profile field's words read (``90.830°``, ``PTP (0)``, ``0x00F0``).

One :class:`ValueFormat` per field (and selector variant) decides, value-free,
how its words become text: word order, signedness, enum, scale and unit, hex
display, range check. :func:`format_value` applies it to words; the notes of
:mod:`mbmon.semantics.notes` are made of these texts.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal

from mbmon.semantics.profile import Field, Variant
from mbmon.semantics.words import s16, u32_to_f32

__all__ = ["ValueFormat", "decimal_point", "format_value", "raw_word", "value_format", "value_text"]

_NO_UNIT_SPACE = frozenset({"°", "%", ""})


def raw_word(f: Field, w: int) -> str:
    if f.display == "hex":
        return f"0x{w & 0xFFFF:04X}"
    return str(w & 0xFFFF if f.type in ("u16", "u32", "version") else s16(w))


def value_text(f: Field, variant: Variant | None, words: Sequence[int]) -> str:
    """The value of field ``f`` (read as ``variant`` says, if any) in its complete ``words``."""
    return format_value(value_format(f, variant), words, 0)


@dataclass(frozen=True, slots=True)
class ValueFormat:
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


def value_format(f: Field, variant: Variant | None) -> ValueFormat:
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
    return ValueFormat(
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
        decimal=decimal_point(scale, spec),
    )


def decimal_point(scale: float | None, spec: str | None) -> tuple[int, str] | None:
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


def format_value(v: ValueFormat, values: Sequence[int], i: int) -> str:
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
