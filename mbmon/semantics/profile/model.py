"""The profile data model: a device register map and the field look-up in it.

A profile (``docs/profiles.md``) describes per Modbus data table the fields a
device exposes: single entries at a fixed address and repeated ranges
(``DO[n]`` at 299+n, ``PR[n]`` blocks of 19 registers with sub-fields). This
module owns the frozen types (:class:`Profile`, :class:`Field`, ...), the
table names and types the loader accepts, :class:`ProfileError`, and answering
"which field sits at this address" in O(1). Reading TOML is
:mod:`~mbmon.semantics.profile.load`, writing it :mod:`~mbmon.semantics.profile.dump`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

TABLES: tuple[str, ...] = ("coils", "discrete_inputs", "input_registers", "holding_registers")
BIT_TABLES = frozenset({"coils", "discrete_inputs"})
#: How notes name a register that has no field name of its own (R201, IR524).
REGISTER_PREFIX: Mapping[str, str] = {"holding_registers": "R", "input_registers": "IR"}
BUILTIN_PROFILES: tuple[str, ...] = ("hrss", "xeg")

#: Words per value for the types whose width is fixed.
TYPE_WORDS: Mapping[str, int] = {"bit": 1, "u16": 1, "s16": 1, "i32": 2, "u32": 2, "f32": 2}
#: Types whose width the entry states with ``words``.
SIZED_TYPES = frozenset({"version", "block"})
REGISTER_TYPES = frozenset(TYPE_WORDS) - {"bit"} | SIZED_TYPES


class ProfileError(ValueError):
    """A profile (or a ``--profile`` binding) that cannot be used, with where and why.

    ``file`` is the file name (or ``<string>``), ``line`` the 1-based line when
    known, ``key`` the dotted path of the offending key (e.g.
    ``holding_registers[3].scale``).
    """

    def __init__(
        self, message: str, *, file: str = "", line: int | None = None, key: str | None = None
    ) -> None:
        self.file = file
        self.line = line
        self.key = key
        self.reason = message
        where = file
        if line is not None:
            where = f"{where}:{line}" if where else f"line {line}"
        super().__init__(f"{where}: {message}" if where else message)


# --------------------------------------------------------------------------- data


@dataclass(frozen=True, slots=True)
class Variant:
    """How a sub-field reads when the group's selector holds a given value (PR[n].type)."""

    name: str | None = None
    label: str | None = None
    unit: str | None = None
    scale: float | None = None


@dataclass(frozen=True, slots=True)
class Field:
    """One profile entry: a single field, a repeated range, or a sub-field of a group.

    ``address`` is the absolute address of a single field, the address of the
    first element (``n == n_range[0]``) of a range, or the offset inside its
    group for a sub-field. A range has ``n_range``; element ``n`` starts at
    ``address + stride * (n - n_range[0])``. A range with ``fields`` is a group
    (``type == "group"``): each element is a block of sub-fields.
    """

    name: str
    address: int
    type: str
    words: int
    label: str | None = None
    description: str | None = None
    scale: float | None = None
    unit: str | None = None
    range: tuple[int, int] | None = None
    enum: Mapping[int, str] | None = None
    enum_style: str = "name"  # "name": "PTP (0)"; "value": "1 (execute)"
    display: str = "dec"  # "dec" | "hex"
    word_order: str = "low_high"  # "low_high" (HRSS, Appendix II) | "high_low" (SWAP_WORD)
    format: str | None = None  # "version": e.g. "V{0}.{1}.{2}.{3}"
    n_range: tuple[int, int] | None = None
    stride: int | None = None
    labels: Mapping[int, str] | None = None  # range: label per n (SI1 Start)
    fields: tuple[Field, ...] = ()
    select: str | None = None  # group: name of the sub-field that picks variants
    variants: Mapping[int, Variant] | None = None  # sub-field: by selector value

    @property
    def is_range(self) -> bool:
        return self.n_range is not None

    @property
    def span(self) -> int:
        """Registers (or bits) one element occupies."""
        return self.stride if self.fields and self.stride else self.words

    def element_name(self, n: int | None) -> str:
        return self.name.replace("{n}", str(n)) if n is not None else self.name

    def end_address(self) -> int:
        """One past the last address the entry covers."""
        if self.n_range is None:
            return self.address + self.words
        first, last = self.n_range
        return self.address + (self.stride or self.words) * (last - first) + self.span


@dataclass(frozen=True, slots=True)
class Channel:
    """A fieldbus channel's share of the address space (inclusive address ranges per table)."""

    name: str
    description: str | None = None
    ranges: Mapping[str, tuple[int, int]] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Note:
    """A documented choice (where the manual contradicts itself) or remark, for docs."""

    title: str
    text: str


@dataclass(frozen=True, slots=True)
class FieldRef:
    """One field instance at a concrete address, as :meth:`Profile.lookup` finds it.

    ``address`` is the first address of the instance, ``n`` the range index,
    ``entry`` the top-level profile entry (the range for elements and
    sub-fields), ``base`` the first address of the group element for sub-fields.
    """

    table: str
    field: Field
    address: int
    n: int | None = None
    entry: Field | None = None
    base: int | None = None

    @property
    def name(self) -> str:
        """Full field name: ``A1``, ``DO[3]``, ``PR[2].Value1`` (selector-independent)."""
        if self.entry is None:
            return self.field.name
        parent = self.entry.element_name(self.n)
        if self.entry.fields:
            return f"{parent}.{self.field.name}"
        return parent

    @property
    def label(self) -> str | None:
        """Short label shown after the name in notes (``Start``, ``motion state``)."""
        if self.entry is not None and not self.entry.fields:
            if self.entry.labels and self.n is not None and self.n in self.entry.labels:
                return self.entry.labels[self.n]
            return self.entry.label
        return self.field.label

    @property
    def words(self) -> int:
        return self.field.words


_MISS = object()


@dataclass(frozen=True)
class Profile:
    """A device register map. Compare with ``==``: source text and path do not count."""

    name: str
    description: str = ""
    session: str | None = None
    #: the function codes the device serves (the manual's list), ``None``: not stated
    functions: tuple[int, ...] | None = None
    tables: Mapping[str, tuple[Field, ...]] = field(default_factory=dict)
    channels: tuple[Channel, ...] = ()
    notes: tuple[Note, ...] = ()
    source: str | None = field(default=None, compare=False, repr=False)
    path: str | None = field(default=None, compare=False)
    _index: dict[str, dict[int, Any]] = field(
        default_factory=dict, init=False, compare=False, repr=False
    )
    _ranges: dict[str, tuple[tuple[int, int, Field], ...]] = field(
        default_factory=dict, init=False, compare=False, repr=False
    )
    #: Views derived from this profile by its readers (the annotator's per-read
    #: layouts), keyed by their owner's keys; each owner bounds its share.
    memo: dict[Any, Any] = field(default_factory=dict, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        for table in TABLES:
            singles: dict[int, Any] = {}
            ranges: list[tuple[int, int, Field]] = []
            for entry in self.tables.get(table, ()):
                if entry.is_range:
                    ranges.append((entry.address, entry.end_address(), entry))
                else:
                    ref = FieldRef(table, entry, entry.address)
                    for a in range(entry.address, entry.address + entry.words):
                        singles[a] = ref
            self._index[table] = singles
            self._ranges[table] = tuple(ranges)

    def entries(self, table: str) -> tuple[Field, ...]:
        return self.tables.get(table, ())

    def lookup(self, table: str, address: int) -> FieldRef | None:
        """The field instance covering ``address`` in ``table`` (a dict hit after the first ask)."""
        index = self._index.get(table)
        if index is None:
            return None
        ref = index.get(address, _MISS)
        if ref is _MISS:
            ref = self._resolve(table, address)
            if len(index) < 200_000:  # memo bound: a hostile scan cannot grow it forever
                index[address] = ref
        return ref  # type: ignore[no-any-return]

    def _resolve(self, table: str, address: int) -> FieldRef | None:
        for start, end, entry in self._ranges[table]:
            if not start <= address < end:
                continue
            first = entry.n_range[0]  # type: ignore[index]
            step = entry.stride or entry.words
            k, off = divmod(address - start, step)
            base = start + k * step
            n = first + k
            if not entry.fields:
                if off < entry.words:
                    return FieldRef(table, entry, base, n, entry, base)
                continue
            for sub in entry.fields:
                if sub.address <= off < sub.address + sub.words:
                    return FieldRef(table, sub, base + sub.address, n, entry, base)
        return None

    def channel_of(self, table: str, address: int) -> Channel | None:
        """Which fieldbus channel an address belongs to, if the profile says."""
        for ch in self.channels:
            r = ch.ranges.get(table)
            if r is not None and r[0] <= address <= r[1]:
                return ch
        return None
