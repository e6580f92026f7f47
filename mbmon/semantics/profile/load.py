"""Reading profiles: TOML text (built-in or user file) checked key by key into a :class:`Profile`.

Every problem is a :class:`~mbmon.semantics.profile.model.ProfileError` that
names the file, the line and the dotted key.
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib import resources
from itertools import pairwise
from pathlib import Path
from typing import Any

from mbmon.protocol.functions import MAX_READ_WORDS
from mbmon.semantics.profile.model import (
    BIT_TABLES,
    BUILTIN_PROFILES,
    REGISTER_TYPES,
    SIZED_TYPES,
    TABLES,
    TYPE_WORDS,
    Channel,
    Field,
    Note,
    Profile,
    ProfileError,
    Variant,
)
from mbmon.semantics.session import is_session, session_names


def builtin_profile_text(name: str) -> str:
    """TOML text of a built-in profile (``hrss``, ``xeg``)."""
    if name not in BUILTIN_PROFILES:
        raise ProfileError(
            f"unknown built-in profile {name!r} (built-in: {', '.join(BUILTIN_PROFILES)})"
        )
    return (resources.files("mbmon.semantics") / "profiles" / f"{name}.toml").read_text("utf-8")


def load_profile(path_or_name: str | Path) -> Profile:
    """Load a built-in profile by name (``hrss``, ``xeg``) or a user profile file."""
    if isinstance(path_or_name, str) and path_or_name in BUILTIN_PROFILES:
        text = builtin_profile_text(path_or_name)
        return loads_profile(text, file=f"{path_or_name}.toml", path=f"builtin:{path_or_name}")
    path = Path(path_or_name)
    try:
        text = path.read_text("utf-8")
    except FileNotFoundError:
        raise ProfileError(
            f"no such profile file, and not a built-in profile ({', '.join(BUILTIN_PROFILES)})",
            file=str(path),
        ) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ProfileError(f"cannot read profile: {e}", file=str(path)) from None
    return loads_profile(text, file=str(path), path=str(path))


_TOML_LINE = re.compile(r"\(at line (\d+), column \d+\)")


def loads_profile(text: str, *, file: str = "<string>", path: str | None = None) -> Profile:
    """Parse and check profile TOML text; ``file`` names it in error messages."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        msg = str(e)
        m = _TOML_LINE.search(msg)
        line = int(m.group(1)) if m else None
        msg = _TOML_LINE.sub("", msg).strip()
        raise ProfileError(f"TOML syntax: {msg}", file=file, line=line) from None
    return _Reader(text, file).profile(doc, path)


class _Reader:
    """Checks a parsed TOML document key by key and builds the :class:`Profile`."""

    def __init__(self, text: str, file: str) -> None:
        self.lines = text.splitlines()
        self.file = file

    # -- errors ------------------------------------------------------------

    def fail(self, where: list[str | int], key: str | None, message: str) -> ProfileError:
        shown = _where(where)
        if key is not None:
            shown = f'{shown} "{key}"' if shown else f'"{key}"'
        dotted = _dotted(where, key)
        return ProfileError(
            f"{shown}: {message}" if shown else message,
            file=self.file,
            line=self.locate(where, key),
            key=dotted,
        )

    def locate(self, where: list[str | int], key: str | None) -> int | None:
        """Best-effort line of a key: follow table headers (``[[t]]`` counted) then the key."""
        headers: list[str] = []
        indexes: list[int | None] = []
        for part in where:
            if isinstance(part, int):
                if indexes:
                    indexes[-1] = part
            else:
                headers.append(part)
                indexes.append(None)
        lineno = 0
        for depth in range(len(headers)):
            name = ".".join(headers[: depth + 1])
            want = indexes[depth]
            count = -1
            found = None
            pat = re.compile(r"^\s*\[\[?\s*" + re.escape(name) + r"\s*\]\]?\s*(#.*)?$")
            for i in range(lineno, len(self.lines)):
                line = self.lines[i]
                if depth > 0 and _is_header(line) and not _header_under(line, headers[:depth]):
                    break  # left the parent element
                if pat.match(line):
                    count += 1
                    if want is None or count == want:
                        found = i
                        break
            if found is None:
                return None
            lineno = found + 1
        if key is None:
            return lineno or None
        kpat = re.compile(r"^\s*(" + re.escape(key) + r'|"' + re.escape(key) + r'")\s*=')
        for i in range(lineno, len(self.lines)):
            line = self.lines[i]
            if _is_header(line) and headers:
                # the key may live in a sub-table header like [t.enum]
                if re.match(r"^\s*\[\[?\s*" + re.escape(".".join([*headers, key])), line):
                    return i + 1
                break
            if kpat.match(line):
                return i + 1
        return None

    # -- typed getters -------------------------------------------------------

    def keys(self, obj: Mapping[str, Any], where: list[str | int], allowed: Iterable[str]) -> None:
        allowed = set(allowed)
        for k in obj:
            if k not in allowed:
                raise self.fail(where, k, f"unknown key (allowed: {', '.join(sorted(allowed))})")

    def table(self, v: Any, where: list[str | int], key: str | None) -> Mapping[str, Any]:
        if not isinstance(v, dict):
            raise self.fail(where, key, f"expected a table, got {_show(v)}")
        return v

    def string(self, v: Any, where: list[str | int], key: str) -> str:
        if not isinstance(v, str):
            raise self.fail(where, key, f"expected a string, got {_show(v)}")
        return v

    def integer(self, v: Any, where: list[str | int], key: str) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(where, key, f"expected an integer, got {_show(v)}")
        return v

    def number(self, v: Any, where: list[str | int], key: str) -> float:
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.fail(where, key, f"expected a number, got {_show(v)}")
        return float(v)

    def pair(self, v: Any, where: list[str | int], key: str) -> tuple[int, int]:
        if (
            not isinstance(v, list)
            or len(v) != 2
            or any(isinstance(x, bool) or not isinstance(x, int) for x in v)
        ):
            raise self.fail(where, key, f"expected [low, high] integers, got {_show(v)}")
        if v[0] > v[1]:
            raise self.fail(where, key, f"low {v[0]} is above high {v[1]}")
        return (v[0], v[1])

    def choice(self, v: Any, where: list[str | int], key: str, options: Iterable[str]) -> str:
        options = tuple(options)
        if v not in options:
            raise self.fail(where, key, f"expected one of {', '.join(options)}, got {_show(v)}")
        return str(v)

    def int_keyed(self, v: Any, where: list[str | int], key: str) -> dict[int, Any]:
        obj = self.table(v, where, key)
        out: dict[int, Any] = {}
        for k, val in obj.items():
            try:
                ik = int(k, 0)
            except ValueError:
                try:
                    ik = int(k, 10)
                except ValueError:
                    raise self.fail(where, key, f"key {k!r} is not an integer") from None
            out[ik] = val
        return out

    def str_map(self, v: Any, where: list[str | int], key: str) -> dict[int, str]:
        out = self.int_keyed(v, where, key)
        for k, val in out.items():
            if not isinstance(val, str):
                raise self.fail(where, key, f"value for {k} must be a string, got {_show(val)}")
        return out

    # -- document ------------------------------------------------------------

    def profile(self, doc: Mapping[str, Any], path: str | None) -> Profile:
        self.keys(doc, [], ("profile", "channels", "notes", *TABLES))
        if "profile" not in doc:
            raise self.fail([], "profile", "missing [profile] header (name, description, session)")
        head = self.table(doc["profile"], [], "profile")
        w: list[str | int] = ["profile"]
        self.keys(head, w, ("name", "description", "session", "functions"))
        if "name" not in head:
            raise self.fail(w, "name", "missing")
        name = self.string(head["name"], w, "name")
        description = self.string(head.get("description", ""), w, "description")
        session = head.get("session")
        if session is not None:
            session = self.session(session, w)
        functions = None if "functions" not in head else self.codes(head["functions"], w)
        tables: dict[str, tuple[Field, ...]] = {}
        for table in TABLES:
            raw = doc.get(table, [])
            if not isinstance(raw, list):
                raise self.fail([], table, f"expected [[{table}]] entries, got {_show(raw)}")
            entries = tuple(self.entry(e, [table, i], table) for i, e in enumerate(raw))
            self.check_overlap(table, entries)
            if entries:
                tables[table] = entries
        channels = tuple(
            self.channel(c, ["channels", i]) for i, c in enumerate(_list(doc, "channels", self))
        )
        notes = tuple(self.note(c, ["notes", i]) for i, c in enumerate(_list(doc, "notes", self)))
        return Profile(
            name=name,
            description=description,
            session=session,
            functions=functions,
            tables=tables,
            channels=channels,
            notes=notes,
            source="\n".join(self.lines) + "\n" if self.lines else "",
            path=path,
        )

    def session(self, v: Any, w: list[str | int]) -> str:
        """The name of a registered device session (:mod:`mbmon.semantics.session`)."""
        name = self.string(v, w, "session")
        if not is_session(name):  # installed plug-ins are looked for only then
            known = ", ".join(session_names())
            raise self.fail(w, "session", f"unknown session {name!r} (known: {known})")
        return name

    def codes(self, v: Any, w: list[str | int]) -> tuple[int, ...]:
        """The function codes a device serves: distinct integers 1..127."""
        if not isinstance(v, list) or not v:
            raise self.fail(w, "functions", f"expected an array of function codes, got {_show(v)}")
        codes = tuple(self.integer(x, w, "functions") for x in v)
        for code in codes:
            if not 0 < code < 0x80:
                raise self.fail(w, "functions", f"function code {code} is outside 1..127")
        if len(set(codes)) != len(codes):
            raise self.fail(w, "functions", f"a function code is listed twice in {list(codes)}")
        return codes

    def channel(self, c: Any, w: list[str | int]) -> Channel:
        c = self.table(c, w, None)
        self.keys(c, w, ("name", "description", *TABLES))
        if "name" not in c:
            raise self.fail(w, "name", "missing")
        ranges = {t: self.pair(c[t], w, t) for t in TABLES if t in c}
        desc = c.get("description")
        return Channel(
            name=self.string(c["name"], w, "name"),
            description=None if desc is None else self.string(desc, w, "description"),
            ranges=ranges,
        )

    def note(self, c: Any, w: list[str | int]) -> Note:
        c = self.table(c, w, None)
        self.keys(c, w, ("title", "text"))
        for k in ("title", "text"):
            if k not in c:
                raise self.fail(w, k, "missing")
        return Note(self.string(c["title"], w, "title"), self.string(c["text"], w, "text"))

    _VALUE_KEYS = (
        "name", "type", "words", "label", "description", "scale", "unit", "range", "enum",
        "enum_style", "display", "word_order", "format",
    )  # fmt: skip

    def entry(self, e: Any, w: list[str | int], table: str, *, sub: bool = False) -> Field:
        """One entry of ``table`` (a sub-field of a group when ``sub``): a group of
        sub-fields (:meth:`group`) or a field with a value (:meth:`value_field`)."""
        e = self.table(e, w, None)
        is_group = "fields" in e
        if sub:
            allowed = {*self._VALUE_KEYS, "offset", "variants"}
        elif is_group:
            allowed = {"name", "description", "label", "address", "n", "stride", "fields", "select"}
        else:
            allowed = {*self._VALUE_KEYS, "address", "n", "stride", "labels"}
        self.keys(e, w, allowed)
        if "name" not in e:
            raise self.fail(w, "name", "missing")
        name = self.string(e["name"], w, "name")
        akey = "offset" if sub else "address"
        if akey not in e:
            raise self.fail(w, akey, "missing")
        address = self.integer(e[akey], w, akey)
        if not 0 <= address <= 0xFFFF:
            raise self.fail(w, akey, f"{address} is outside 0..65535")
        n_range = None
        if is_group and "n" not in e:
            raise self.fail(w, "fields", 'sub-fields need a repeated range ("n = [first, last]")')
        if "n" in e:
            n_range = self.pair(e["n"], w, "n")
            if "{n}" not in name:
                raise self.fail(
                    w, "name", f'a repeated range needs "{{n}}" in its name, got {name!r}'
                )
        head = _Head(
            name, address, n_range, _opt(e, "label", w, self.string),
            _opt(e, "description", w, self.string),
        )  # fmt: skip
        if is_group:
            return self.group(e, w, table, head)
        return self.value_field(e, w, table, head)

    def group(self, e: Mapping[str, Any], w: list[str | int], table: str, head: _Head) -> Field:
        """A repeated block of sub-fields (``PR[n]``), with an optional selector."""
        subs = e["fields"]
        if not isinstance(subs, list) or not subs:
            raise self.fail(w, "fields", f"expected [[{table}.fields]] entries, got {_show(subs)}")
        fields = tuple(
            self.entry(s, [*w, "fields", i], table, sub=True) for i, s in enumerate(subs)
        )
        names = [f.name for f in fields]
        dup = {x for x in names if names.count(x) > 1}
        if dup:
            raise self.fail(w, "fields", f"duplicate sub-field name {sorted(dup)[0]!r}")
        span = max(f.address + f.words for f in fields)
        self.check_overlap(table, fields, where=[*w, "fields"], what="offset")
        stride = span if "stride" not in e else self.integer(e["stride"], w, "stride")
        if stride < span:
            raise self.fail(w, "stride", f"{stride} is smaller than the sub-fields' span {span}")
        select = _opt(e, "select", w, self.string)
        if select is not None:
            sel = next((f for f in fields if f.name == select), None)
            if sel is None:
                raise self.fail(w, "select", f"no sub-field named {select!r}")
            if sel.words != 1:
                raise self.fail(w, "select", f"selector {select!r} must be one register")
        else:
            for i, f in enumerate(fields):
                if f.variants:
                    raise self.fail(
                        [*w, "fields", i], "variants", 'variants need "select" on the range'
                    )
        self.check_end(w, head.address, head.n_range, stride, span)
        return Field(
            name=head.name, address=head.address, type="group", words=span, label=head.label,
            description=head.description, n_range=head.n_range, stride=stride, fields=fields,
            select=select,
        )  # fmt: skip

    def value_field(
        self, e: Mapping[str, Any], w: list[str | int], table: str, head: _Head
    ) -> Field:
        """A field with a value: its type and width, the value keys (checked against the
        type), labels of a range, variants of a sub-field, and where it ends."""
        ftype, words = self.width(e, w, table in BIT_TABLES)
        v = self.value_keys(e, w, ftype, words)
        labels = None
        if "labels" in e:
            labels = self.labels(e["labels"], w, head.n_range)
        variants = None if "variants" not in e else self.variants(e["variants"], w)
        stride = None
        if head.n_range is not None:
            stride = words if "stride" not in e else self.integer(e["stride"], w, "stride")
            if stride < words:
                raise self.fail(
                    w, "stride", f"{stride} is smaller than the field's {words} word(s)"
                )
            self.check_end(w, head.address, head.n_range, stride, words)
        elif head.address + words > 0x10000:
            raise self.fail(w, "address", f"{head.address}+{words} words runs past 65535")
        return Field(
            name=head.name, address=head.address, type=ftype, words=words, label=head.label,
            description=head.description, n_range=head.n_range, stride=stride, labels=labels,
            variants=variants, **v,
        )  # fmt: skip

    def width(self, e: Mapping[str, Any], w: list[str | int], bits: bool) -> tuple[str, int]:
        """A field's type and how many words it takes (``words`` for the sized types)."""
        ftype = self.choice(
            e.get("type", "bit" if bits else "s16"),
            w,
            "type",
            ("bit",) if bits else sorted(REGISTER_TYPES),
        )
        if ftype in SIZED_TYPES:
            if "words" not in e:
                raise self.fail(w, "words", f'type "{ftype}" needs "words"')
            words = self.integer(e["words"], w, "words")
            if not 1 <= words <= MAX_READ_WORDS:
                raise self.fail(w, "words", f"{words} is outside 1..{MAX_READ_WORDS}")
            return ftype, words
        words = TYPE_WORDS[ftype]
        if "words" in e and self.integer(e["words"], w, "words") != words:
            raise self.fail(w, "words", f'type "{ftype}" is {words} word(s), got {e["words"]}')
        return ftype, words

    def value_keys(
        self, e: Mapping[str, Any], w: list[str | int], ftype: str, words: int
    ) -> dict[str, Any]:
        """The keys that say how a value reads (:data:`_VALUE_READERS`, :data:`_CHOICES`),
        each read by its getter and checked against the type (:data:`_NOT_FOR`)."""
        v: dict[str, Any] = {}
        for key, getter in _VALUE_READERS:
            v[key] = None if key not in e else getattr(self, getter)(e[key], w, key)
        for key, options in _CHOICES:
            v[key] = self.choice(e.get(key, options[0]), w, key, options)
        for key, value, types, why in _NOT_FOR:
            if key in e and (value is None or v[key] == value) and ftype in types:
                raise self.fail(w, key, why.format(type=ftype))
        if v["scale"] == 0:
            raise self.fail(w, "scale", "must not be 0")
        if "word_order" in e and words != 2:
            raise self.fail(w, "word_order", "only for two-register types (i32, u32, f32)")
        if ftype == "version":
            v["format"] = self.version_format(v["format"], w, words)
        elif v["format"] is not None:
            raise self.fail(w, "format", 'only for type "version"')
        return v

    def version_format(self, fmt: str | None, w: list[str | int], words: int) -> str:
        """The format of a ``version`` field (default: its words joined by dots)."""
        if fmt is None:
            return ".".join("{%d}" % i for i in range(words))  # noqa: UP031
        try:
            fmt.format(*range(words))
        except (IndexError, KeyError, ValueError) as err:
            raise self.fail(w, "format", f"bad format {fmt!r} for {words} words: {err}") from None
        return fmt

    def labels(self, v: Any, w: list[str | int], n_range: tuple[int, int] | None) -> dict[int, str]:
        """Labels of some elements of a repeated range, by ``n``."""
        if n_range is None:
            raise self.fail(w, "labels", 'only for a repeated range ("n = [first, last]")')
        labels = self.str_map(v, w, "labels")
        lo, hi = n_range
        for k in labels:
            if not lo <= k <= hi:
                raise self.fail(w, "labels", f"n = {k} is outside {lo}..{hi}")
        return labels

    def variants(self, v: Any, w: list[str | int]) -> dict[int, Variant]:
        """How a sub-field reads per value of its group's selector."""
        out = {}
        vw: list[str | int] = [*w, "variants"]
        for k, item in self.int_keyed(v, w, "variants").items():
            item = self.table(item, vw, str(k))
            where = [*vw, str(k)]
            self.keys(item, where, ("name", "label", "unit", "scale"))
            out[k] = Variant(
                name=_opt(item, "name", where, self.string),
                label=_opt(item, "label", where, self.string),
                unit=_opt(item, "unit", where, self.string),
                scale=_opt(item, "scale", where, self.number),
            )
        return out

    def check_end(
        self,
        w: list[str | int],
        address: int,
        n_range: tuple[int, int] | None,
        stride: int,
        span: int,
    ) -> None:
        if n_range is None:
            return
        end = address + stride * (n_range[1] - n_range[0]) + span
        if end > 0x10000:
            raise self.fail(w, "n", f"element {n_range[1]} ends at {end - 1}, past 65535")

    def check_overlap(
        self,
        table: str,
        entries: tuple[Field, ...],
        *,
        where: list[str | int] | None = None,
        what: str = "address",
    ) -> None:
        spans = sorted(
            ((f.address, f.end_address(), i) for i, f in enumerate(entries)), key=lambda s: s[:2]
        )
        for (_a0, a1, i), (b0, _b1, j) in pairwise(spans):
            if b0 < a1:
                w = where if where is not None else [table]
                late, early = (j, i) if j > i else (i, j)  # blame the one written later
                e, o = entries[late], entries[early]
                raise self.fail(
                    [*w, late],
                    what,
                    f"{e.name!r} ({e.address}..{e.end_address() - 1}) overlaps "
                    f"{o.name!r} ({o.address}..{o.end_address() - 1})",
                )


@dataclass(frozen=True, slots=True)
class _Head:
    """What every entry has: name, address (offset in a group), range, label, description."""

    name: str
    address: int
    n_range: tuple[int, int] | None
    label: str | None
    description: str | None


#: the optional keys of a value, in the order they are read, and the reader of each
_VALUE_READERS: tuple[tuple[str, str], ...] = (
    ("scale", "number"),
    ("unit", "string"),
    ("range", "pair"),
    ("enum", "str_map"),
    ("format", "string"),
)
#: the keys with a fixed set of values, the default first
_CHOICES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("enum_style", ("name", "value")),
    ("display", ("dec", "hex")),
    ("word_order", ("low_high", "high_low")),
)
#: (key, value or None for any, the types it is not for, the message)
_NOT_FOR: tuple[tuple[str, str | None, frozenset[str], str], ...] = (
    ("enum", None, frozenset({"bit", "block", "version", "f32"}), 'not allowed for type "{type}"'),
    ("scale", None, frozenset({"bit", "block", "version"}), 'not allowed for type "{type}"'),
    ("display", "hex", frozenset({"bit", "f32"}), '"hex" not allowed for type "{type}"'),
)


def _list(doc: Mapping[str, Any], key: str, r: _Reader) -> list[Any]:
    v = doc.get(key, [])
    if not isinstance(v, list):
        raise r.fail([], key, f"expected [[{key}]] entries, got {_show(v)}")
    return v


def _opt(obj: Mapping[str, Any], key: str, w: list[str | int], get: Any) -> Any:
    return None if key not in obj else get(obj[key], w, key)


def _is_header(line: str) -> bool:
    return line.lstrip().startswith("[")


def _header_under(line: str, parents: list[str]) -> bool:
    inner = line.strip().strip("[]").strip()
    return inner.startswith(".".join(parents) + ".")


def _where(where: list[str | int]) -> str:
    out = ""
    for part in where:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else part
    return out


def _dotted(where: list[str | int], key: str | None) -> str:
    base = _where(where)
    if key is None:
        return base
    return f"{base}.{key}" if base else key


def _show(v: Any) -> str:
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, dict):
        return "a table"
    if isinstance(v, list):
        return f"an array {json.dumps(v, ensure_ascii=False, default=str)}"
    return str(v)
