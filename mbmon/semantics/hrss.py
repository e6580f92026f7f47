"""HRSS command reconstruction: the R200/R201..R251 handshake as a lifecycle of commands.

A client drives an HRSS controller by writing a command number to R201 and its
parameters to R202..R251 (FC 06/10/17, in any number of requests), then R200 = 1
to execute; the controller answers in IR200 (1 success, 2 fail), IR201 (current
action) and, for the Get commands, IR202..IR251; the client resets R200 = 0
before the next command (manual §5.3.3.5, Tables 14-43).

:class:`HrssSession` follows that handshake for one server endpoint and unit,
from pairing steps (:class:`~mbmon.model.Transaction`). It keeps the register
image seen so far, turns it into :class:`~mbmon.model.CommandUpdate` steps with
the command in HRSS program form, decodes Get returns, warns about protocol
misuse and keeps the robot state (joint angles, pose, speeds, errors, motion).

Every command layout, enum, range and state register comes from
``profiles/hrss_commands.toml``; this module is the code that reads it.
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from types import MappingProxyType
from typing import Any

from mbmon.model import (
    Annotation,
    CommandUpdate,
    Frame,
    Kind,
    Phase,
    Stream,
    Transaction,
    TxStatus,
)
from mbmon.semantics.words import join_i32, join_u32, s16, u16

__all__ = [
    "CommandSpec",
    "Decoded",
    "Field",
    "Form",
    "HrssSession",
    "Layout",
    "Spec",
    "decode_command",
    "decode_returns",
    "format_scaled",
    "iter_layouts",
    "load_spec",
    "parse_spec",
]

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


# --------------------------------------------------------------------------- text


def format_scaled(raw: int, decimals: int) -> str:
    """``raw`` * 10**-decimals without trailing zeros.

    (90830, 3) -> ``90.83``; (90000, 3) -> ``90``; (-399958, 3) -> ``-399.958``.
    """
    if decimals <= 0:
        return str(raw)
    whole, frac = divmod(abs(raw), 10**decimals)
    digits = f"{frac:0{decimals}d}".rstrip("0")
    text = f"{whole}.{digits}" if digits else str(whole)
    return "-" + text if raw < 0 and text != "0" else text


def _show(f: Field, raw: int | None, spec: Spec) -> str:
    if raw is None:
        return "?"
    if f.enum is not None:
        name = spec.enums[f.enum].get(raw)
        return name if name is not None else f"{raw}?"
    if f.scale != 1 and f.decimals and abs(f.scale - 10.0**-f.decimals) < 1e-12:
        return format_scaled(raw, f.decimals)
    if f.scale != 1:
        return f"{raw * f.scale:g}"
    return str(raw)


_OPTIONAL = re.compile(r"\[\[(.*?)\]\]")
_TOKEN = re.compile(r"<([^<>]*)>|\{(\w+)\}")


def _render(
    template: str, fields: Mapping[str, Field], raws: Mapping[str, int | None], spec: Spec
) -> str:
    """Fill a layout's text template (syntax documented in hrss_commands.toml)."""

    def shown(name: str) -> bool:
        f = fields.get(name)
        if f is None:
            return False
        if f.show_if is None:
            return True
        ctl = raws.get(f.show_if)
        return ctl is not None and ctl != 0

    def names(part: str) -> list[str]:
        out: list[str] = []
        for m in _TOKEN.finditer(part):
            out.extend(m.group(1).split() if m.group(1) is not None else [m.group(2)])
        return out

    def token(m: re.Match[str]) -> str:
        if m.group(1) is not None:
            items = [
                f"{fields[n].label or n} {_show(fields[n], raws.get(n), spec)}"
                for n in m.group(1).split()
                if shown(n)
            ]
            return "{" + ", ".join(items) + "}"
        n = m.group(2)
        f = fields.get(n)
        return _show(f, raws.get(n), spec) if f is not None else "{" + n + "}"

    def optional(m: re.Match[str]) -> str:
        inner = m.group(1)
        return _TOKEN.sub(token, inner) if all(shown(n) for n in names(inner)) else ""

    return _TOKEN.sub(token, _OPTIONAL.sub(optional, template))


# --------------------------------------------------------------------------- pure decoding


@dataclass(frozen=True, slots=True)
class Decoded:
    """A command (or Get returns) as the registers say it.

    ``params`` maps field names to scaled numbers (enum fields keep their
    number), plus ``command`` (name) and ``table``; ``problems`` lists values
    outside the manual's ranges and unknown numbers; ``regs`` are the registers
    a complete block needs (the command number register not included);
    ``missing`` are those of them never seen.
    """

    code: int | None
    name: str
    text: str
    table: int | None
    params: Mapping[str, Any]
    problems: tuple[str, ...]
    regs: frozenset[int]
    missing: frozenset[int]
    layout: Layout | None = None


def _decode_form(
    form: Form,
    read: Callable[[int], int | None],
    spec: Spec,
    name: str,
    code: int | None,
    prefix: str,
) -> Decoded:
    layout, sel = form.pick(read)
    params: dict[str, Any] = {"command": name}
    problems: list[str] = []
    if form.select is not None:
        params[form.select.name] = sel
        if sel is not None and (layout is None or form.select.out_of_range(sel)):
            problems.append(_range_text(form.select, sel, prefix))
    if layout is None:
        regs = form.regs(None)
        what = form.select.name.replace("_", " ") if form.select else "layout"
        text = f"{name} ({what} {'?' if sel is None else sel})"
        return Decoded(
            code,
            name,
            text,
            form.table,
            MappingProxyType(params),
            tuple(problems),
            regs,
            frozenset(r for r in regs if read(r) is None),
        )
    byname = {f.name: f for f in layout.fields}
    raws = {f.name: f.raw(read) for f in layout.fields}
    for f in layout.fields:
        raw = raws[f.name]
        params[f.name] = None if raw is None else (raw if f.enum else f.value(raw))
        if raw is not None and f.out_of_range(raw):
            problems.append(_range_text(f, raw, prefix))
    params["table"] = layout.table
    regs = form.regs(layout)
    return Decoded(
        code=code,
        name=name,
        text=_render(layout.text, byname, raws, spec),
        table=layout.table,
        params=MappingProxyType(params),
        problems=tuple(problems),
        regs=regs,
        missing=frozenset(r for r in regs if read(r) is None),
        layout=layout,
    )


def _range_text(f: Field, raw: int, prefix: str) -> str:
    lo = "" if f.min is None else str(f.min)
    hi = "" if f.max is None else str(f.max)
    where = "..".join(f"{prefix}{r}" for r in f.regs)
    return f"{f.name} {raw} outside {lo}..{hi} ({where})"


def _reader(image: Mapping[int, int]) -> Callable[[int], int | None]:
    return image.get


def decode_command(holding: Mapping[int, int], spec: Spec | None = None) -> Decoded:
    """The command that holding registers R201..R251 describe (values as unsigned words)."""
    spec = spec or load_spec()
    read = _reader(holding)
    raw_code = read(spec.reg("command_reg"))
    if raw_code is None:
        return Decoded(
            None,
            "?",
            "command ? (R201 never seen)",
            None,
            MappingProxyType({"command": None}),
            (),
            frozenset(),
            frozenset(),
        )
    code = s16(raw_code)
    cmd = spec.commands.get(code)
    if cmd is None:
        return Decoded(
            code,
            f"command {code}",
            f"unknown command {code}",
            None,
            MappingProxyType({"command": None}),
            (f"command number {code} not in Table 16 (R201)",),
            frozenset(),
            frozenset(),
        )
    return _decode_form(cmd.params, read, spec, cmd.name, code, "R")


def decode_returns(
    code: int, inputs: Mapping[int, int], spec: Spec | None = None
) -> Decoded | None:
    """The returns of Get command ``code`` in input registers IR202.. (``None``: no returns)."""
    spec = spec or load_spec()
    cmd = spec.commands.get(code)
    if cmd is None or cmd.returns is None:
        return None
    return _decode_form(cmd.returns, _reader(inputs), spec, cmd.name, code, "IR")


# --------------------------------------------------------------------------- session


@dataclass(slots=True)
class _Exec:
    """One executed command, from R200 = 1 to its end."""

    decoded: Decoded
    spec: CommandSpec | None
    t0: float
    stream: Stream
    done: bool = False  # IR200 showed 1/2, or the execute was rejected
    status: int | None = None
    settled: bool = False  # completion seen another way (motion ended, hold-to-run stopped)
    looked: bool = False  # the client read IR200 or IR524 after the execute
    moving: bool = False  # IR524 showed Running/Hold/Delay after the execute
    warned: bool = False  # "never completes" already said
    return_seen: set[int] = field(default_factory=set)
    returned: tuple[Any, ...] | None = None


@dataclass(slots=True)
class _Write:
    """A write request applied to the holding image, kept until its answer."""

    old: dict[int, int | None]
    new: dict[int, int]
    execute: _Exec | None = None


_MOVING = (2, 3, 4)  # IR524 Running, Hold, Delay


class HrssSession:
    """Per (server endpoint, unit): the register image seen so far and the command protocol.

    Writes (FC 06, 10, 0x16, 17) update the holding image when the *request* is
    seen, so that a command executes on the frame that carries R200 = 1; the
    written registers stay unconfirmed until the answer, and an exception
    answer puts the old values back. Reads (FC 03, 04, 17) update the images
    from the answer. ``complete_timeout`` (seconds of capture time, default from
    the TOML) bounds how long a command may go without completing while the
    client is watching IR200/IR524.
    """

    def __init__(self, stream: Stream, unit: int, *, complete_timeout: float | None = None) -> None:
        self.stream = stream
        self.unit = unit
        self._spec = load_spec()
        p = self._spec
        self._exec_reg = p.reg("execute_reg")
        self._cmd_reg = p.reg("command_reg")
        self._params = range(p.reg("param_first"), p.reg("param_last") + 1)
        self._returns = range(p.reg("return_first"), p.reg("return_last") + 1)
        self._timeout = float(
            complete_timeout if complete_timeout is not None else p.protocol["complete_timeout"]
        )
        self._holding: dict[int, int] = {}
        self._inputs: dict[int, int] = {}
        self._unconfirmed: set[int] = set()
        self._writes: dict[tuple[Any, ...], _Write] = {}
        self._block: set[int] = set()  # R201..R251 written since the last execute
        self._block_code: int | None = None  # command whose WRITTEN was emitted for the block
        self._active: _Exec | None = None  # last executed command
        self._get: _Exec | None = None  # last executed command that has returns
        self._motion: int | None = None
        self._queue_over = False
        self._state: dict[str, float] = {}

    # ------------------------------------------------------------------ public views

    @property
    def state(self) -> dict[str, float]:
        """Current robot state (a copy): keys and units in docs/commands.md."""
        return dict(self._state)

    @property
    def holding(self) -> Mapping[int, int]:
        """Holding register image (address -> unsigned word), writes applied on request."""
        return MappingProxyType(self._holding)

    @property
    def inputs(self) -> Mapping[int, int]:
        """Input register image (address -> unsigned word) from FC 04 answers."""
        return MappingProxyType(self._inputs)

    @property
    def unconfirmed(self) -> frozenset[int]:
        """Holding registers written by a request whose answer has not been seen."""
        return frozenset(self._unconfirmed)

    # ------------------------------------------------------------------ feed

    def feed(self, tx: Transaction) -> Annotation:
        """Follow one pairing step: the notes, command steps and state change it causes."""
        out = _Out(self, tx)
        frame = tx.request if tx.request is not None else tx.response
        if frame is None or frame.unit != self.unit:
            return Annotation()
        req = tx.request
        if tx.status is TxStatus.PENDING and req is not None:
            self._request(req, out)
        elif tx.status is TxStatus.ANSWERED and req is not None and tx.response is not None:
            key = _key(req)
            if key not in self._writes:
                self._request(req, out)  # the request was never fed on its own
            self._confirm(key)
            self._answer(req, tx.response, out)
        elif tx.status is TxStatus.EXCEPTION and req is not None:
            self._rejected(req, tx.response, out)  # a write never fed as PENDING: nothing to undo
        elif tx.status is TxStatus.TIMEOUT and req is not None:
            self._writes.pop(_key(req), None)  # values stay, still unconfirmed
        self._check_timeout(tx.ts, out)
        return out.annotation()

    # ------------------------------------------------------------------ writes

    def _request(self, req: Frame, out: _Out) -> None:
        pdu = req.pdu
        if pdu.kind is not Kind.REQUEST:
            return
        writes: list[tuple[int, int | None]] = []
        if pdu.fc == 0x06 and pdu.address is not None and pdu.values:
            writes = [(pdu.address, pdu.values[0])]
        elif pdu.fc == 0x10 and pdu.address is not None and pdu.values is not None:
            writes = [(pdu.address + i, v) for i, v in enumerate(pdu.values)]
        elif pdu.fc == 0x17:
            addr = pdu.fields.get("write_address")
            vals = pdu.fields.get("write_values")
            if addr is not None and vals is not None:
                writes = [(addr + i, v) for i, v in enumerate(vals)]
        elif pdu.fc == 0x16 and pdu.address is not None:
            old = self._holding.get(pdu.address)
            and_m, or_m = pdu.fields.get("and_mask"), pdu.fields.get("or_mask")
            if old is None or and_m is None or or_m is None:
                writes = [(pdu.address, None)]  # result unknown
            else:
                writes = [(pdu.address, (old & and_m) | (or_m & ~and_m & 0xFFFF))]
        if not writes:
            return
        w = _Write(old={a: self._holding.get(a) for a, _ in writes}, new={})
        for a, v in writes:
            if v is None:
                self._holding.pop(a, None)
            else:
                self._holding[a] = v
                w.new[a] = v
            self._unconfirmed.add(a)
        self._writes[_key(req)] = w
        while len(self._writes) > 256:
            self._writes.pop(next(iter(self._writes)))
        self._commands(w, req.ts, out)

    def _commands(self, w: _Write, ts: float, out: _Out) -> None:
        params = {a for a in w.new if a == self._cmd_reg or a in self._params}
        execute = w.new.get(self._exec_reg)
        before = w.old.get(self._exec_reg)
        if params:
            new_code = w.new.get(self._cmd_reg)
            if (
                self._block_code is not None
                and new_code is not None
                and (s16(new_code) != self._block_code)
            ):
                self._block.clear()  # a different command is being written
                self._block_code = None
            self._block |= params
        if execute == 1:
            self._execute(w, before, ts, out)
        elif params and self._block_code is None:
            dec = decode_command(self._holding, self._spec)
            covered = dec.regs <= self._block
            if dec.code is not None and dec.layout is not None and covered and not dec.missing:
                self._block_code = dec.code
                out.command(
                    Phase.WRITTEN,
                    dec.text,
                    dec.code,
                    params=dec.params,
                    note=f"written: {dec.text}",
                )
        if execute == 0 and before == 1:
            a = self._active
            if a is not None and a.spec is not None and a.spec.hold_to_run and not a.settled:
                a.settled = True
                out.note(f"stop: {a.decoded.text} (R200 = 0 after {ts - a.t0:.3f} s)")
        elif execute is not None and execute not in (0, 1):
            out.warn(
                f"R200 = {s16(execute)} outside 0..1: not an execute or a reset",
                kind="range",
                code=None,
            )

    def _execute(self, w: _Write, before: int | None, ts: float, out: _Out) -> None:
        dec = decode_command(self._holding, self._spec)
        old = self._active
        if old is not None and not old.done and not old.settled and old.looked and not old.warned:
            old.warned = True
            out.warn(
                f"never completed: {old.decoded.text} (no IR200 status before the next "
                f"execute, {ts - old.t0:.3f} s)",
                kind="never_completed",
                code=old.decoded.code,
            )
        cmd = self._spec.commands.get(dec.code) if dec.code is not None else None
        ex = _Exec(decoded=dec, spec=cmd, t0=ts, stream=out.stream)
        self._active = ex
        w.execute = ex
        if cmd is not None and cmd.returns is not None:
            self._get = ex
        self._block.clear()
        self._block_code = None
        if before == 1:
            out.warn(
                f"execute without reset: R200 was still 1 when {dec.text} was executed "
                "(reset R200 = 0 first, §5.3.3.5)",
                kind="no_reset",
                code=dec.code,
            )
        out.command(
            Phase.EXECUTING, dec.text, dec.code, params=dec.params, note=f"execute: {dec.text}"
        )
        if dec.problems:
            out.warn(
                f"out of range in {dec.text}: " + "; ".join(dec.problems),
                kind="range",
                code=dec.code,
            )

    def _confirm(self, key: tuple[Any, ...]) -> None:
        w = self._writes.pop(key, None)
        if w is None:
            return
        for a, v in w.new.items():
            if self._holding.get(a) == v:
                self._unconfirmed.discard(a)

    def _rejected(self, req: Frame, resp: Frame | None, out: _Out) -> None:
        w = self._writes.pop(_key(req), None)
        if w is None:
            return
        exc = resp.pdu.exception_code if resp is not None else None
        for a, old in w.old.items():
            if a in w.new and self._holding.get(a) != w.new[a]:
                continue  # written again since: keep the newer value
            if old is None:
                self._holding.pop(a, None)
            else:
                self._holding[a] = old
            self._unconfirmed.discard(a)
        lo, hi = min(w.old), max(w.old)
        span = f"R{lo}" if lo == hi else f"R{lo}..R{hi}"
        out.note(f"write rejected (exception {exc}): {span} unchanged")
        ex = w.execute
        if ex is not None and not ex.done:
            ex.done = True
            out.warn(
                f"execute rejected (exception {exc}): {ex.decoded.text}",
                kind="rejected",
                code=ex.decoded.code,
            )

    # ------------------------------------------------------------------ reads

    def _answer(self, req: Frame, resp: Frame, out: _Out) -> None:
        rq, rs = req.pdu, resp.pdu
        if rs.kind is not Kind.RESPONSE or rs.values is None or rq.address is None:
            return
        values = rs.values
        if rq.count is not None:
            values = values[: rq.count]
        if rq.fc in (0x03, 0x17):
            for i, v in enumerate(values):
                self._holding[rq.address + i] = v
                self._unconfirmed.discard(rq.address + i)
        elif rq.fc == 0x04:
            got = {rq.address + i: v for i, v in enumerate(values)}
            self._inputs.update(got)
            self._inputs_read(got, resp.ts, out)

    def _inputs_read(self, got: Mapping[int, int], ts: float, out: _Out) -> None:
        p = self._spec
        status_reg = p.reg("status_reg")
        if status_reg in got:
            self._status(s16(got[status_reg]), got, ts, out)
        if any(r in self._returns for r in got):
            self._returns_read(got, ts, out)
        queue_reg = p.reg("queue_reg")
        if queue_reg in got:
            q = s16(got[queue_reg])
            limit = int(p.protocol["queue_max"])
            if q > limit and not self._queue_over:
                out.warn(
                    f"{q} commands queued (IR102 > {limit}): motion commands will fail",
                    kind="queue",
                    code=None,
                )
            self._queue_over = q > limit
        motion_reg = p.reg("motion_reg")
        if motion_reg in got:
            self._motion_read(s16(got[motion_reg]), ts, out)
        self._state_read(got, out)

    def _status(self, v: int, got: Mapping[int, int], ts: float, out: _Out) -> None:
        a = self._active
        if a is None or a.done or ts < a.t0:
            return
        a.looked = True
        if v not in (1, 2):
            return
        a.done, a.status = True, v
        phase = Phase.SUCCESS if v == 1 else Phase.FAIL
        params = dict(a.decoded.params)
        params["status"] = v
        action_reg = self._spec.reg("action_reg")
        if action_reg in got:
            params["action"] = s16(got[action_reg])
        dur = ts - a.t0
        word = "success" if v == 1 else "fail"
        out.command(
            phase,
            a.decoded.text,
            a.decoded.code,
            params=params,
            duration=dur,
            note=f"{word}: {a.decoded.text} ({dur:.3f} s)",
        )

    def _returns_read(self, got: Mapping[int, int], ts: float, out: _Out) -> None:
        g = self._get
        if g is None or ts < g.t0 or g.status == 2 or g.decoded.code is None:
            return
        g.return_seen.update(r for r in got if r in self._returns)
        seen = {r: v for r, v in self._inputs.items() if r in g.return_seen}
        dec = decode_returns(g.decoded.code, seen, self._spec)
        if dec is None or dec.layout is None or dec.missing:
            return
        values = tuple(sorted((k, v) for k, v in dec.params.items()))
        if values == g.returned:
            return
        g.returned = values
        out.command(
            Phase.RETURNED, dec.text, dec.code, params=dec.params, note=f"returned: {dec.text}"
        )
        spec = g.spec
        key = spec.returns.match if spec is not None and spec.returns is not None else None
        if key is not None:
            asked, got_back = g.decoded.params.get(key), dec.params.get(key)
            if asked is not None and got_back is not None and asked != got_back:
                out.warn(
                    f"{g.decoded.text} returned {dec.text.split(' = ')[0]}: stale returns?",
                    kind="stale_returns",
                    code=dec.code,
                )
        if dec.problems:
            out.note("returns out of range: " + "; ".join(dec.problems))

    def _motion_read(self, v: int, ts: float, out: _Out) -> None:
        prev = self._motion
        self._motion = v
        if v != prev:
            lab = self._spec.label("motion_state", v)
            out.note(
                f"motion: {lab}"
                if prev is None
                else f"motion: {self._spec.label('motion_state', prev)} -> {lab}"
            )
        a = self._active
        if a is None or ts < a.t0 or a.spec is None or not a.spec.motion:
            return
        a.looked = True
        if v in _MOVING:
            a.moving = True
        elif v == 1 and a.moving and not a.settled:
            a.settled = True
            out.note(f"motion done: {a.decoded.text} ({ts - a.t0:.3f} s after R200 = 1)")

    def _state_read(self, got: Mapping[int, int], out: _Out) -> None:
        for key, f in self._spec.state:
            raw = f.raw(got.get)  # both words from this very answer
            if raw is None:
                continue
            val = float(f.value(raw))
            if self._state.get(key) != val:
                self._state[key] = val
                out.state_changed = True

    # ------------------------------------------------------------------ completion

    def _check_timeout(self, ts: float, out: _Out) -> None:
        a = self._active
        if a is None or a.done or a.settled or a.warned or not a.looked:
            return
        if ts - a.t0 <= self._timeout:
            return
        if a.spec is not None and a.spec.hold_to_run and self._holding.get(self._exec_reg) == 1:
            return  # JOG / GO HOME run while R200 = 1
        if a.moving and self._motion in _MOVING:
            return  # still moving
        a.warned = True
        why = (
            "robot never moved"
            if a.spec is not None and a.spec.motion and not a.moving
            else "no IR200 status"
        )
        out.warn(
            f"never completed: {a.decoded.text} ({why} {self._timeout:g} s after R200 = 1)",
            kind="never_completed",
            code=a.decoded.code,
        )


def _key(req: Frame) -> tuple[Any, ...]:
    return (req.ts, req.stream.id, req.tid, req.raw)


class _Out:
    """What one feed produces, gathered in order."""

    def __init__(self, session: HrssSession, tx: Transaction) -> None:
        self.session = session
        self.ts = tx.ts
        frame = tx.request if tx.request is not None else tx.response
        self.stream = frame.stream if frame is not None else session.stream
        self.unit = session.unit
        self.notes: list[str] = []
        self.commands: list[CommandUpdate] = []
        self.state_changed = False

    def note(self, text: str) -> None:
        self.notes.append(text)

    def command(
        self,
        phase: Phase,
        text: str,
        code: int | None,
        *,
        params: Mapping[str, Any],
        duration: float | None = None,
        note: str | None = None,
    ) -> None:
        self.commands.append(
            CommandUpdate(
                ts=self.ts,
                stream=self.stream,
                unit=self.unit,
                phase=phase,
                text=text,
                code=code,
                duration=duration,
                params=MappingProxyType(dict(params)),
            )
        )
        if note is not None:
            self.notes.append(note)

    def warn(self, text: str, *, kind: str, code: int | None) -> None:
        self.command(Phase.WARNING, text, code, params={"warning": kind}, note=f"warning: {text}")

    def annotation(self) -> Annotation:
        return Annotation(
            notes=tuple(self.notes),
            commands=tuple(self.commands),
            state=self.session.state if self.state_changed else None,
        )


def iter_layouts(spec: Spec | None = None) -> Iterable[tuple[CommandSpec, str, Layout]]:
    """Every (command, "params"|"returns", layout) of the spec, for docs and tests."""
    spec = spec or load_spec()
    for cmd in spec.commands.values():
        for lay in cmd.params.layouts:
            yield cmd, "params", lay
        if cmd.returns is not None:
            for lay in cmd.returns.layouts:
                yield cmd, "returns", lay
