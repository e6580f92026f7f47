"""HRSS registers as commands: decode a register image and render it in HRSS program form.

Pure functions of a register image and the :class:`~mbmon.semantics.hrss.spec.Spec`:
:func:`decode_command` (R201..R251), :func:`decode_returns` (IR202..IR251 of a
Get command), :func:`parameter_rows` (the written command registers named for the
monitor's robot panel) and the text templates of ``hrss_commands.toml``.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from mbmon.semantics.hrss.spec import Field, Form, Layout, Spec, load_spec
from mbmon.semantics.words import s16


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
    return decode_command_from(_reader(holding), spec or load_spec())


def decode_command_from(read: Callable[[int], int | None], spec: Spec) -> Decoded:
    """:func:`decode_command` of the image ``read`` gives (``None``: a register never seen).

    What it returns depends only on the words ``read`` gives for the registers it
    asks for, so a caller may remember results by those words.
    """
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


def parameter_rows(
    holding: Mapping[int, int],
    unconfirmed: frozenset[int] = frozenset(),
    spec: Spec | None = None,
) -> list[tuple[str, str, str, bool]]:
    """The written command registers R200..R251 as ``(registers, name, value, confirmed)``.

    Names and values come from the HRSS command spec (``hrss_commands.toml``):
    the execute and command registers by their protocol keys, R202..R251 by
    the fields of the layout the command in R201 (and its select register)
    picks, one row per field (``R203..R204 A1 90 deg``); written registers no
    field names show their unsigned word. ``holding`` is a session's holding
    image (unsigned words); ``unconfirmed`` those whose write is unanswered.
    This is the HRSS session's panel (:meth:`HrssSession.panel`).
    """
    spec = spec or load_spec()
    execute, command = spec.reg("execute_reg"), spec.reg("command_reg")
    first, last = min(execute, command), spec.reg("param_last")
    written = {a: v for a, v in holding.items() if first <= a <= last}
    if not written:
        return []
    rows: list[tuple[str, str, str, bool]] = []
    shown: set[int] = set()
    names = {v: k.removesuffix("_reg") for k, v in spec.protocol.items() if k in (
        "execute_reg", "command_reg")}  # fmt: skip

    if execute in written:
        value = s16(written[execute])
        rows.append((f"R{execute}", names[execute], spec.label("execute", value),
                     execute not in unconfirmed))  # fmt: skip
        shown.add(execute)
    decoded = decode_command(written, spec)
    if command in written:
        text = f"{decoded.name} ({decoded.code})" if decoded.code is not None else decoded.name
        rows.append((f"R{command}", names[command], text, command not in unconfirmed))
        shown.add(command)
    fields = []
    cmd = spec.commands.get(decoded.code) if decoded.code is not None else None
    if cmd is not None and cmd.params.select is not None:
        fields.append(cmd.params.select)
    if decoded.layout is not None:
        fields.extend(decoded.layout.fields)
    for f in fields:
        raw = f.raw(written.get)
        if raw is None or f.reg in shown:
            continue
        if f.enum is not None:
            text = spec.label(f.enum, raw)
        elif f.scale != 1 and f.decimals and abs(f.scale - 10.0**-f.decimals) < 1e-12:
            text = format_scaled(raw, f.decimals)
        else:
            text = f"{f.value(raw):g}"
        if f.unit and "|" not in f.unit:
            text += f" {f.unit}" if f.unit != "%" else "%"
        rows.append((f.where(), f.label or f.name, text, not (set(f.regs) & unconfirmed)))
        shown.update(f.regs)
    for address in sorted(set(written) - shown):
        rows.append((f"R{address}", "", str(written[address]), address not in unconfirmed))
    return rows
