"""The HRSS command spec: ``profiles/hrss_commands.toml`` as frozen data.

Every command layout (Table 16 and the parameter tables), enum, range and
state register of the R200..R251 handshake comes from that TOML; this module
reads and checks it (:func:`load_spec`, parsed once) and owns the types the
renderer and the session read: :class:`Field`, :class:`Layout`,
:class:`Form`, :class:`CommandSpec`, :class:`Spec`.
"""

from __future__ import annotations

import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from types import MappingProxyType
from typing import Any

from mbmon.semantics.words import join_i32, join_u32, s16, u16

_PROFILE = "hrss_commands.toml"

# --------------------------------------------------------------------------- data model of the TOML


@dataclass(frozen=True, slots=True)
class Field:
    """One parameter, return value or state value: where its words are and how to read them."""

    name: str
    reg: int
    type: str = "s16"  # s16 | u16 | i32 | u32
    scale: float = 1.0
    unit: str = ""
    label: str = ""
    min: int | None = None
    max: int | None = None
    enum: str | None = None
    show_if: str | None = None

    @property
    def regs(self) -> tuple[int, ...]:
        """Registers this field occupies (low word first for 32-bit types)."""
        return (self.reg, self.reg + 1) if self.type in ("i32", "u32") else (self.reg,)

    @property
    def decimals(self) -> int:
        """Digits after the point that ``scale`` gives (0.001 -> 3)."""
        return _decimals(self.scale)

    def raw(self, read: Callable[[int], int | None]) -> int | None:
        """The unscaled integer, or ``None`` when a word of it was never seen."""
        words = [read(r) for r in self.regs]
        if any(w is None for w in words):
            return None
        if self.type == "i32":
            return join_i32(words[0], words[1])  # type: ignore[arg-type]
        if self.type == "u32":
            return join_u32(words[0], words[1])  # type: ignore[arg-type]
        if self.type == "u16":
            return u16(words[0])  # type: ignore[arg-type]
        return s16(words[0])  # type: ignore[arg-type]

    def value(self, raw: int) -> int | float:
        """The scaled number (an int when the scale is 1)."""
        if self.scale == 1:
            return raw
        d = self.decimals
        if d and abs(self.scale - 10.0**-d) < 1e-12:
            return raw / 10**d
        return raw * self.scale

    def out_of_range(self, raw: int) -> bool:
        return (self.min is not None and raw < self.min) or (
            self.max is not None and raw > self.max
        )

    def where(self) -> str:
        return "..".join(f"R{r}" for r in self.regs)


@dataclass(frozen=True, slots=True)
class Layout:
    """The registers and text of one command variant (one table of the manual)."""

    when: tuple[int, ...] | None
    table: int | None
    text: str
    fields: tuple[Field, ...]

    @property
    def regs(self) -> frozenset[int]:
        return frozenset(r for f in self.fields for r in f.regs)


@dataclass(frozen=True, slots=True)
class Form:
    """Parameters or returns of a command: one layout, or several picked by a select field."""

    table: int | None
    layouts: tuple[Layout, ...]
    select: Field | None = None
    match: str | None = None

    def pick(self, read: Callable[[int], int | None]) -> tuple[Layout | None, int | None]:
        """The layout that applies to the registers, and the select value that chose it."""
        if self.select is None:
            return self.layouts[0], None
        v = self.select.raw(read)
        if v is None:
            return None, None
        for lay in self.layouts:
            if lay.when is not None and v in lay.when:
                return lay, v
        return None, v

    def regs(self, layout: Layout | None) -> frozenset[int]:
        """Registers a complete block of this form needs (layout + select register)."""
        regs = set(layout.regs) if layout is not None else set()
        if self.select is not None:
            regs.update(self.select.regs)
        return frozenset(regs)


@dataclass(frozen=True, slots=True)
class CommandSpec:
    """One command of Table 16 with its parameter form and, for Get commands, its returns."""

    code: int
    name: str
    table: int | None
    params: Form
    returns: Form | None = None
    motion: bool = False
    hold_to_run: bool = False


@dataclass(frozen=True, slots=True)
class Spec:
    """Everything hrss_commands.toml says."""

    protocol: Mapping[str, Any]
    enums: Mapping[str, Mapping[int, str]]
    state: tuple[tuple[str, Field], ...]
    commands: Mapping[int, CommandSpec]

    def reg(self, key: str) -> int:
        return int(self.protocol[key])

    def label(self, enum: str, value: int | None) -> str:
        """``Running (2)``-style label of an enum value."""
        if value is None:
            return "?"
        name = self.enums.get(enum, {}).get(value)
        return f"{name} ({value})" if name is not None else f"unknown ({value})"


@lru_cache(maxsize=256)  # a handful of scales per spec: bounded all the same
def _decimals(scale: float) -> int:
    if scale == 1:
        return 0
    text = f"{scale:.12f}".rstrip("0")
    return len(text.split(".")[1]) if "." in text else 0


def _field(d: Mapping[str, Any], where: str) -> Field:
    try:
        return Field(
            name=str(d["name"]) if "name" in d else str(d["key"]),
            reg=int(d["reg"]),
            type=str(d.get("type", "s16")),
            scale=float(d.get("scale", 1)),
            unit=str(d.get("unit", "")),
            label=str(d.get("label", d.get("name", ""))),
            min=d.get("min"),
            max=d.get("max"),
            enum=d.get("enum"),
            show_if=d.get("show_if"),
        )
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{_PROFILE}: bad field in {where}: {err!r} ({dict(d)})") from err


def _form(d: Mapping[str, Any], where: str) -> Form:
    layouts = []
    for i, lay in enumerate(d.get("layouts", ())):
        w = f"{where} layout {i + 1}"
        when = lay.get("when")
        layouts.append(
            Layout(
                when=tuple(int(v) for v in when) if when is not None else None,
                table=lay.get("table"),
                text=str(lay["text"]),
                fields=tuple(_field(f, w) for f in lay.get("fields", ())),
            )
        )
    if not layouts:
        raise ValueError(f"{_PROFILE}: {where} has no layouts")
    select = _field(d["select"], f"{where} select") if "select" in d else None
    if select is None and len(layouts) != 1:
        raise ValueError(f"{_PROFILE}: {where} has several layouts but no select")
    if select is not None and any(lay.when is None for lay in layouts):
        raise ValueError(f"{_PROFILE}: {where}: every layout needs 'when' with a select")
    return Form(table=d.get("table"), layouts=tuple(layouts), select=select, match=d.get("match"))


def parse_spec(data: Mapping[str, Any]) -> Spec:
    """Build a :class:`Spec` from the parsed TOML (raises ValueError naming what is wrong)."""
    enums = {
        name: MappingProxyType({int(k): str(v) for k, v in table.items()})
        for name, table in data.get("enums", {}).items()
    }
    state = tuple((str(s["key"]), _field(s, f"state {s.get('key')}")) for s in data["state"])
    commands: dict[int, CommandSpec] = {}
    for c in data["commands"]:
        where = f"command {c.get('code')} {c.get('name')}"
        params = _form(c, where)
        returns = _form(c["returns"], f"{where} returns") if "returns" in c else None
        code = int(c["code"])
        if code in commands:
            raise ValueError(f"{_PROFILE}: command number {code} defined twice")
        commands[code] = CommandSpec(
            code=code,
            name=str(c["name"]),
            table=c.get("table"),
            params=params,
            returns=returns,
            motion=bool(c.get("motion", False)),
            hold_to_run=bool(c.get("hold_to_run", False)),
        )
    for cmd in commands.values():
        for form in (cmd.params, cmd.returns):
            if form is None:
                continue
            for lay in form.layouts:
                for f in lay.fields:
                    if f.enum is not None and f.enum not in enums:
                        raise ValueError(f"{_PROFILE}: {cmd.name}: unknown enum {f.enum!r}")
    return Spec(
        protocol=MappingProxyType(dict(data["protocol"])),
        enums=MappingProxyType(enums),
        state=state,
        commands=MappingProxyType(commands),
    )


@lru_cache(maxsize=1)
def load_spec() -> Spec:
    """The built-in command layouts (parsed once)."""
    text = resources.files("mbmon.semantics").joinpath("profiles", _PROFILE).read_bytes()
    return parse_spec(tomllib.loads(text.decode("utf-8")))


def iter_layouts(spec: Spec | None = None) -> Iterable[tuple[CommandSpec, str, Layout]]:
    """Every (command, "params"|"returns", layout) of the spec, for docs and tests."""
    spec = spec or load_spec()
    for cmd in spec.commands.values():
        for lay in cmd.params.layouts:
            yield cmd, "params", lay
        if cmd.returns is not None:
            for lay in cmd.returns.layouts:
                yield cmd, "returns", lay
