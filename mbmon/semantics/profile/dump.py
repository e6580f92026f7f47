"""Writing profiles back to TOML: ``loads_profile(dump_profile(p)) == p``."""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from typing import Any

from mbmon.semantics.profile.model import SIZED_TYPES, TABLES, Field, Profile


def dump_profile(profile: Profile) -> str:
    """TOML text of a profile; ``loads_profile(dump_profile(p)) == p``."""
    out: list[str] = ["[profile]", f"name = {_tv(profile.name)}"]
    if profile.description:
        out.append(f"description = {_tv(profile.description)}")
    if profile.session is not None:
        out.append(f"session = {_tv(profile.session)}")
    if profile.functions is not None:
        out.append(f"functions = {_tv(list(profile.functions))}")
    for ch in profile.channels:
        out += ["", "[[channels]]", f"name = {_tv(ch.name)}"]
        if ch.description is not None:
            out.append(f"description = {_tv(ch.description)}")
        for t in TABLES:
            if t in ch.ranges:
                out.append(f"{t} = {_tv(list(ch.ranges[t]))}")
    for note in profile.notes:
        out += ["", "[[notes]]", f"title = {_tv(note.title)}", f"text = {_tv(note.text)}"]
    for table in TABLES:
        for entry in profile.entries(table):
            out += ["", f"[[{table}]]", *_dump_field(entry, sub=False)]
            for sub in entry.fields:
                out += ["", f"[[{table}.fields]]", *_dump_field(sub, sub=True)]
    return "\n".join(out) + "\n"


def _dump_field(f: Field, *, sub: bool) -> list[str]:
    kv: list[tuple[str, Any]] = [("name", f.name), ("offset" if sub else "address", f.address)]
    if f.n_range is not None:
        kv.append(("n", list(f.n_range)))
    if f.fields:
        kv.append(("stride", f.stride))
        kv += [("label", f.label), ("description", f.description), ("select", f.select)]
        return [f"{k} = {_tv(v)}" for k, v in kv if v is not None]
    if f.n_range is not None and f.stride != f.words:
        kv.append(("stride", f.stride))
    kv.append(("type", f.type))
    if f.type in SIZED_TYPES:
        kv.append(("words", f.words))
    kv += [
        ("word_order", f.word_order if f.word_order != "low_high" else None),
        ("label", f.label),
        ("description", f.description),
        ("scale", f.scale),
        ("unit", f.unit),
        ("range", list(f.range) if f.range else None),
        ("display", f.display if f.display != "dec" else None),
        ("format", f.format),
        ("enum_style", f.enum_style if f.enum_style != "name" else None),
        ("enum", f.enum),
        ("labels", f.labels),
    ]
    if f.variants is not None:
        kv.append(
            (
                "variants",
                {
                    k: {
                        a: getattr(v, a)
                        for a in ("name", "label", "unit", "scale")
                        if getattr(v, a) is not None
                    }
                    for k, v in f.variants.items()
                },
            )
        )
    return [f"{k} = {_tv(v)}" for k, v in kv if v is not None]


def _tv(v: Any) -> str:
    """One TOML value (inline tables on one line, as TOML 1.0 requires)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        r = repr(v)
        return r if any(c in r for c in ".en") else r + ".0"
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_tv(x) for x in v) + "]"
    if isinstance(v, Mapping):
        items = ", ".join(f"{_tk(k)} = {_tv(x)}" for k, x in v.items())
        return "{ " + items + " }" if items else "{}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _tk(k: Any) -> str:
    s = str(k)
    return s if re.fullmatch(r"[A-Za-z0-9_-]+", s) else json.dumps(s, ensure_ascii=False)
