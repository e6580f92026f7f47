"""Whether a payload read back from a log can be trusted: the fields of mbmon's topics
against their JSON schemas (``mbmon/schemas``), fast for the common yes.

Every reader of a log (``replay``, ``info``, ``export``, ``--redecode``) asks
:func:`payload_problem` of each decoded payload before it uses a field; the
topics and schemas themselves are :mod:`mbmon.io.mcap.layout`'s.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Mapping
from typing import Any

from mbmon.io.mcap.layout import TOPIC_FRAMES, TOPIC_SCHEMAS, frame_chunk, schema_text

_INT_MIN, _INT_END = -(1 << 63), 1 << 64  # what a JSON integer of a log may be (64 bits)
_SURROGATE = re.compile("[\ud800-\udfff]")


def payload_problem(topic: str, obj: Any) -> str | None:
    """Why a decoded message payload of ``topic`` cannot be trusted, or ``None``.

    Every reader of a log (``replay``, ``info``, ``export``, ``--redecode``) asks
    this before using a payload's fields: the payload must be a JSON object
    whose fields match the types of the topic's schema (``mbmon/schemas``;
    integers within 64 bits, finite numbers, strings without lone surrogates,
    enums and nested objects as declared). Fields the schema does not name are
    not judged, and a missing field is not damage (older logs lack newer
    ones): readers take ``None`` for it. Topics without a schema pass.
    """
    checker = _checkers.get(topic)
    if checker is None:
        name = TOPIC_SCHEMAS.get(topic)
        if name is None:
            return None if isinstance(obj, dict) else f"payload is {_kind_of(obj)}, not an object"
        schema = json.loads(schema_text(name))
        checker = _checkers[topic] = (schema, _compile(schema))
    schema, fits = checker
    if fits(obj):  # the fast yes; the walk below says why not
        if topic == TOPIC_FRAMES and "chunk" in obj:  # format 4's marker (not in the schema)
            return _chunk_problem(obj)
        return None
    if not isinstance(obj, dict):
        return f"payload is {_kind_of(obj)}, not a JSON object"
    return _problem(schema, obj, "") or "payload does not match its schema"


def _chunk_problem(obj: dict[str, Any]) -> str | None:
    """Why a /modbus/frames object with ``chunk`` (log format 4: the frame stands for a
    chunk left out of /modbus/raw) cannot be trusted, or ``None``: ``chunk`` must be a
    direction and the object hold what the chunk is rebuilt from."""
    try:
        frame_chunk(obj)
    except ValueError as exc:
        return f"chunk: {exc}"
    return None


_checkers: dict[str, tuple[Any, Callable[[Any], bool]]] = {}
_ABSENT = object()


def _int_ok(v: int) -> bool:
    return _INT_MIN <= v < _INT_END


def _str_ok(v: str) -> bool:
    return v.isascii() or _SURROGATE.search(v) is None


#: schema type -> {Python type: extra test (None: none)}
_TYPE_TESTS: dict[str, dict[type, Callable[[Any], bool] | None]] = {
    "integer": {int: _int_ok},
    "number": {int: _int_ok, float: math.isfinite},
    "string": {str: _str_ok},
    "null": {type(None): None},
    "boolean": {bool: None},
    "array": {list: None},
    "object": {dict: None},
}


#: schema keys that only describe (a field whose schema has just these and "type" is a
#: type test alone)
_TYPE_ONLY = frozenset({"type", "description", "title", "$comment", "contentEncoding"})
_JSON_TYPES = (dict, list, str, int, float, bool, type(None))


def _compile(schema: Mapping[str, Any]) -> Callable[[Any], bool]:
    """A fast yes/no test of ``value`` against a schema node (what :func:`_problem` judges)."""
    tests: list[Callable[[Any], bool]] = []
    consts = [schema["const"]] if "const" in schema else schema.get("enum")
    if consts is not None:
        allowed = frozenset((type(c), c) for c in consts)
        tests.append(lambda v: type(v) not in (list, dict) and (type(v), v) in allowed)
    if "oneOf" in schema:
        subs = [_compile(s) for s in schema["oneOf"]]
        tests.append(lambda v: any(t(v) for t in subs))
    wanted = schema.get("type")
    if wanted is not None:
        typemap: dict[type, Any] = {}
        for name in (wanted,) if isinstance(wanted, str) else wanted:
            typemap.update(_TYPE_TESTS[name])

        def typed(v: Any) -> bool:
            f = typemap.get(type(v), False)
            return f is None or (f is not False and f(v))

        tests.append(typed)
    low, high = schema.get("minimum"), schema.get("maximum")
    if low is not None or high is not None:
        lo = -math.inf if low is None else low
        hi = math.inf if high is None else high
        tests.append(lambda v: type(v) not in (int, float) or lo <= v <= hi)
    if "items" in schema:
        item = _compile(schema["items"])
        tests.append(lambda v: type(v) is not list or all(map(item, v)))
    if "properties" in schema:
        # per field: {Python type: None (fits) or a test of the value} when the field's
        # schema is a type alone (most are), else every type to its compiled test
        props: list[tuple[str, dict[type, Any]]] = []
        for key, sub in schema["properties"].items():
            if set(sub) <= _TYPE_ONLY and "type" in sub:
                names = (sub["type"],) if isinstance(sub["type"], str) else sub["type"]
                field_types: dict[type, Any] = {}
                for name in names:
                    field_types.update(_TYPE_TESTS[name])
            else:
                full = _compile(sub)
                field_types = {t: full for t in _JSON_TYPES}
            props.append((key, field_types))

        def fields(v: Any) -> bool:
            if type(v) is not dict:
                return True  # the type test judges it
            get = v.get
            for key, types in props:
                x = get(key, _ABSENT)
                if x is _ABSENT:
                    continue
                f = types.get(type(x), False)
                if f is not None and (f is False or not f(x)):
                    return False
            return True

        tests.append(fields)
    if not tests:
        return lambda v: True
    if len(tests) == 1:
        return tests[0]
    if len(tests) == 2:
        first, second = tests
        return lambda v: first(v) and second(v)
    return lambda v: all(t(v) for t in tests)


def _problem(schema: Mapping[str, Any], value: Any, path: str) -> str | None:
    """The first way ``value`` differs from the schema subset mbmon's schemas use."""
    where = path or "payload"
    if "const" in schema and not _same(value, schema["const"]):
        return f"{where} is {_kind_of(value)}, not {schema['const']!r}"
    if "enum" in schema and not any(_same(value, c) for c in schema["enum"]):
        return f"{where} is {_kind_of(value)}, not one of {schema['enum']}"
    if "oneOf" in schema and all(_problem(s, value, path) for s in schema["oneOf"]):
        return f"{where} is {_kind_of(value)}, not one of the schema's values"
    wanted = schema.get("type")
    if wanted is not None:
        types = (wanted,) if isinstance(wanted, str) else wanted
        if not any(_is(value, t) for t in types):
            return f"{where} is {_kind_of(value)} where the schema has {' or '.join(types)}"
    if isinstance(value, int | float) and not isinstance(value, bool):
        low, high = schema.get("minimum"), schema.get("maximum")
        if (low is not None and value < low) or (high is not None and value > high):
            return f"{where} is {value!r}, out of range"
    elif isinstance(value, list) and "items" in schema:
        for i, item in enumerate(value):
            why = _problem(schema["items"], item, f"{path}[{i}]")
            if why:
                return why
    elif isinstance(value, dict) and "properties" in schema:
        for key, sub in schema["properties"].items():
            if key in value:
                why = _problem(sub, value[key], f"{path}.{key}" if path else key)
                if why:
                    return why
    return None


def _is(value: Any, kind: str) -> bool:
    t = type(value)
    if kind == "integer":
        return t is int and _INT_MIN <= value < _INT_END
    if kind == "number":
        return (t is int and _INT_MIN <= value < _INT_END) or (t is float and math.isfinite(value))
    if kind == "string":
        return t is str and (value.isascii() or _SURROGATE.search(value) is None)
    if kind == "null":
        return value is None
    return t is {"boolean": bool, "array": list, "object": dict}.get(kind)


def _same(value: Any, constant: Any) -> bool:
    return type(value) is type(constant) and value == constant


def _kind_of(value: Any) -> str:
    """A short description of a damaged value for a message (never the whole value)."""
    if value is None or isinstance(value, bool):
        return json.dumps(value)
    if isinstance(value, int):
        return str(value) if abs(value) < 10**20 else f"an integer of {value.bit_length()} bits"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return repr(value) if len(value) <= 20 else f"a string of {len(value)} characters"
    return f"a JSON {'array' if isinstance(value, list) else 'object'}"
