"""Log format 3's and 4's protobuf messages: ``/modbus/frames`` and ``/modbus/raw`` as
``modbus.Frame`` and ``modbus.Raw`` (``mbmon/schemas/modbus.log4.proto``: format 3's
``modbus.log3.proto``, kept for reference, with ``Frame.chunk`` added; a format-3
message decodes the same, the field absent).

What this module owns: the one reading of that ``.proto`` file (the fields of each
message), the FileDescriptorSet a log's schema records carry (what Foxglove and any
protobuf reader decode the messages with), the encoder the pure writer uses, and the
decoder every mbmon reader uses, which gives the format-2 JSON object of the record
back member for member (docs/logs.md, "Format versions").

The mapping is exact both ways. A member is stored in its field when the field holds
its value as it is (an ``int`` that is no ``bool`` in an int64, a ``float`` in a
double, a ``str`` in a string, a non-empty list of ints or strings in a repeated
field, ``pdu`` as bytes when its text is the canonical upper-case hex, ``data`` as
bytes when its text is canonical base64); every other member (null, an empty list, a
value out of range, nested objects such as ``fields``, ``info``, ``command``) is kept
in ``extra``, the JSON object of those members. The decoder puts the members back in
the order the writers make them.

No protobuf runtime is needed: varints, 64-bit doubles and length-delimited fields
are written and read here. The decoder is strict, as a log may be damaged or hostile:
a truncated field, a wire type that is not the field's, text that is not UTF-8, an
``extra`` that is not a JSON object give :class:`ProtoError`; unknown fields are
passed over, as protobuf does.
"""

from __future__ import annotations

import base64
import binascii
import json
import re
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cache
from importlib import resources
from typing import Any

__all__ = [
    "FRAME_SCHEMA",
    "RAW_SCHEMA",
    "ProtoError",
    "decode_frame",
    "decode_payload",
    "decode_raw",
    "descriptor_set",
    "encode_frame",
    "encode_raw",
    "varint",
]

#: the schema names (MCAP schema records, encoding "protobuf")
FRAME_SCHEMA = "modbus.Frame"
RAW_SCHEMA = "modbus.Raw"
PROTO_FILE = "modbus.log4.proto"

_INT64_MIN = -(1 << 63)
_INT64_MAX = (1 << 63) - 1
_DOUBLE = struct.Struct("<d")

#: the member orders the writers make: a frame's is the ``read --json`` object's
_FRAME_ORDER = (
    "index", "time", "stream", "src", "dst", "transport", "tid", "unit", "fc", "kind",
    "exception_code", "address", "count", "values", "pdu", "line", "notes", "crc_ok",
    "latency_ms", "malformed", "request_index",
)  # fmt: skip
_CHUNK_ORDER = (
    "type", "stream", "transport", "client", "server", "timed", "direction", "ts", "data",
)  # fmt: skip
_EVENT_ORDER = (
    "type", "stream", "transport", "client", "server", "timed", "ts", "direction", "data",
    "event", "info",
)  # fmt: skip


class ProtoError(ValueError):
    """A protobuf message that is not a valid ``modbus.Frame`` / ``modbus.Raw``."""


@dataclass(frozen=True, slots=True)
class _Field:
    name: str
    number: int
    type: str  # int64, double, bool, string, bytes
    repeated: bool


_FIELD_LINE = re.compile(
    r"^\s*(optional|repeated)\s+(\w+)\s+(\w+)\s*=\s*(\d+)\s*(\[\s*packed\s*=\s*true\s*\])?\s*;"
)
_TYPES = {"int64": 3, "double": 1, "bool": 8, "string": 9, "bytes": 12}  # FieldDescriptorProto


def _proto_text() -> str:
    return resources.files("mbmon.schemas").joinpath(PROTO_FILE).read_text(encoding="utf-8")


@cache
def messages() -> dict[str, tuple[_Field, ...]]:
    """The messages of the ``.proto`` file: full name -> its fields, in file order."""
    package = ""
    out: dict[str, tuple[_Field, ...]] = {}
    current: list[_Field] | None = None
    name = ""
    for raw_line in _proto_text().splitlines():
        line = raw_line.split("//", 1)[0].strip()
        if not line:
            continue
        if line.startswith("package "):
            package = line[len("package ") :].rstrip(";").strip()
        elif line.startswith("message "):
            name = line.split()[1]
            current = []
        elif line == "}" and current is not None:
            out[f"{package}.{name}"] = tuple(current)
            current = None
        elif current is not None:
            m = _FIELD_LINE.match(line)
            if m is None or m.group(2) not in _TYPES:
                raise ValueError(f"{PROTO_FILE}: cannot read {line!r}")
            current.append(
                _Field(m.group(3), int(m.group(4)), m.group(2), m.group(1) == "repeated")
            )
    return out


# ---------------------------------------------------------------------------- encoding


def _varint(n: int, out: bytearray) -> None:
    n &= 0xFFFF_FFFF_FFFF_FFFF
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)


def varint(n: int) -> bytes:
    """``n`` as a protobuf varint (a negative int64 as its ten-byte two's complement)."""
    out = bytearray()
    _varint(n, out)
    return bytes(out)


def _key(number: int, wire: int, out: bytearray) -> None:
    _varint(number << 3 | wire, out)


def _len_field(number: int, data: bytes, out: bytearray) -> None:
    _key(number, 2, out)
    _varint(len(data), out)
    out += data


@cache
def descriptor_set() -> bytes:
    """The FileDescriptorSet (``google.protobuf.FileDescriptorSet``) of the ``.proto``
    file, as a log's protobuf schema records carry it."""
    fdp = bytearray()
    _len_field(1, PROTO_FILE.encode(), fdp)  # name
    package = FRAME_SCHEMA.split(".")[0]
    _len_field(2, package.encode(), fdp)  # package
    for full, fields in messages().items():
        msg = bytearray()
        _len_field(1, full.split(".")[-1].encode(), msg)
        for f in fields:
            fd = bytearray()
            _len_field(1, f.name.encode(), fd)
            _key(3, 0, fd)
            _varint(f.number, fd)
            _key(4, 0, fd)
            _varint(3 if f.repeated else 1, fd)  # LABEL_REPEATED / LABEL_OPTIONAL
            _key(5, 0, fd)
            _varint(_TYPES[f.type], fd)
            _len_field(10, _json_name(f.name).encode(), fd)
            if f.repeated and f.type in ("int64", "double", "bool"):
                _len_field(8, b"\x10\x01", fd)  # FieldOptions.packed = true
            _len_field(2, bytes(fd), msg)
        _len_field(4, bytes(msg), fdp)  # message_type
    _len_field(12, b"proto2", fdp)  # syntax
    out = bytearray()
    _len_field(1, bytes(fdp), out)
    return bytes(out)


def _json_name(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(p[:1].upper() + p[1:] for p in rest)


def _hex_of(data: bytes) -> str:
    return data.hex(" ").upper()


#: small varints made once (most values a log holds: units, function codes, registers),
#: by the first :func:`_plan`: a run that imports this module and writes no message
#: this way (the compiled core writes its own) never pays for the 16,384 of them
_SMALL: list[bytes] = []


@cache
def _plan(schema: str) -> dict[str, tuple[str, bytes, bool, int]]:
    """A message's fields by name: (type, key bytes as written, repeated, number); the
    first call makes :data:`_SMALL`, which :func:`_encode` reads after its plan."""
    if not _SMALL:
        _SMALL.extend(
            bytes([n]) if n < 0x80 else bytes([(n & 0x7F) | 0x80, n >> 7]) for n in range(1 << 14)
        )
    plan = {}
    for f in messages()[schema]:
        wire = (
            1
            if f.type == "double"
            else (0 if f.type in ("int64", "bool") and not f.repeated else 2)
        )
        plan[f.name] = (f.type, varint(f.number << 3 | wire), f.repeated, f.number)
    return plan


def _encode(schema: str, obj: Mapping[str, Any]) -> bytes:
    """``obj``'s members in their fields, the rest in ``extra``."""
    out = bytearray()
    extra: dict[str, Any] = {}
    plan = _plan(schema)
    small = _SMALL
    last = bytearray()  # format 4's chunk marker: after every other field, extra too
    for key, value in obj.items():
        p = plan.get(key)
        if p is None or key == "extra":
            extra[key] = value
        elif p[0] == "int64" and type(value) is int and 0 <= value < 16384 and not p[2]:
            out += p[1]  # the common member inline: a small count, unit, code, index
            out += small[value]
        elif not _put(p, key, value, last if key == "chunk" else out):
            extra[key] = value
    if extra:
        text = json.dumps(extra, separators=(",", ":"))  # ASCII: lone surrogates too
        _len_field(plan["extra"][3], text.encode("ascii"), out)
    return bytes(out + last)


def _put(p: tuple[str, bytes, bool, int], name: str, value: Any, out: bytearray) -> bool:
    """Write ``value`` as field ``p`` (of :func:`_plan`) when the field holds it exactly;
    else False (and nothing written)."""
    t, key, repeated, _ = p
    if repeated:
        return _put_list(t, key, value, out)
    vt = type(value)
    if t == "int64":
        if vt is not int:
            return False
        if 0 <= value < 16384:
            out += key
            out += _SMALL[value]
            return True
        if not _INT64_MIN <= value <= _INT64_MAX:
            return False
        out += key
        _varint(value, out)
    elif t == "double":
        if vt is not float:
            return False
        out += key
        out += _DOUBLE.pack(value)
    elif t == "string":
        if vt is not str:
            return False
        try:
            data = value.encode("utf-8")
        except UnicodeEncodeError:  # lone surrogates: only JSON can keep them
            return False
        out += key
        _varint(len(data), out)
        out += data
    elif t == "bool":
        if vt is not bool:
            return False
        out += key
        out.append(1 if value else 0)
    else:  # bytes: pdu as canonical hex text, data as canonical base64 text
        data = _text_bytes(name, value)
        if data is None:
            return False
        out += key
        _varint(len(data), out)
        out += data
    return True


def _put_list(t: str, key: bytes, value: Any, out: bytearray) -> bool:
    """A repeated field's values (packed int64s, or strings), as :func:`_put`."""
    if type(value) is not list or not value:
        return False
    if t == "int64":
        if set(map(type, value)) != {int}:
            return False
        if 0 <= min(value) and max(value) < 0x80:
            body = bytearray(value)  # one byte a value (bits, small registers)
        elif _INT64_MIN <= min(value) and max(value) <= _INT64_MAX:
            body = bytearray()
            for v in value:
                _varint(v, body)
        else:
            return False
        out += key
        _varint(len(body), out)
        out += body
        return True
    if t != "string" or any(type(v) is not str for v in value):
        return False
    try:
        items = [v.encode("utf-8") for v in value]
    except UnicodeEncodeError:
        return False
    for data in items:
        out += key
        _varint(len(data), out)
        out += data
    return True


def _text_bytes(name: str, value: Any) -> bytes | None:
    if type(value) is not str:
        return None
    try:
        if name == "pdu":
            data = bytes.fromhex(value)
            return data if _hex_of(data) == value else None
        data = base64.b64decode(value, validate=True)
        return data if base64.b64encode(data).decode("ascii") == value else None
    except (ValueError, binascii.Error):
        return None


def encode_frame(obj: Mapping[str, Any]) -> bytes:
    """A format-2 ``/modbus/frames`` object as a ``modbus.Frame`` message."""
    return _encode(FRAME_SCHEMA, obj)


def encode_raw(obj: Mapping[str, Any]) -> bytes:
    """A format-2 ``/modbus/raw`` object as a ``modbus.Raw`` message."""
    return _encode(RAW_SCHEMA, obj)


# ---------------------------------------------------------------------------- decoding


def _read_varint(data: bytes, p: int) -> tuple[int, int]:
    n = shift = 0
    end = len(data)
    while True:
        if p >= end:
            raise ProtoError("a varint runs past the end of the message")
        b = data[p]
        p += 1
        n |= (b & 0x7F) << shift
        if not b & 0x80:
            return n, p
        shift += 7
        if shift >= 70:
            raise ProtoError("a varint longer than 10 bytes")


def _signed(n: int) -> int:
    n &= 0xFFFF_FFFF_FFFF_FFFF
    return n - (1 << 64) if n >> 63 else n


def _decode(fields: tuple[_Field, ...], data: bytes) -> dict[str, Any]:
    by_number = {f.number: f for f in fields}
    got: dict[str, Any] = {}
    p = 0
    end = len(data)
    while p < end:
        key, p = _read_varint(data, p)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise ProtoError("field number 0")
        f = by_number.get(number)
        value: int | bytes
        if wire == 0:
            value, p = _read_varint(data, p)
        elif wire == 1:
            if p + 8 > end:
                raise ProtoError("a 64-bit field runs past the end of the message")
            value = data[p : p + 8]
            p += 8
        elif wire == 2:
            n, p = _read_varint(data, p)
            if n > end - p:
                raise ProtoError("a length-delimited field runs past the end of the message")
            value = data[p : p + n]
            p += n
        elif wire == 5:
            if p + 4 > end:
                raise ProtoError("a 32-bit field runs past the end of the message")
            p += 4
            continue
        else:
            raise ProtoError(f"wire type {wire} (groups are not used)")
        if f is None:
            continue  # an unknown field: passed over
        _take(f, wire, value, got)
    return got


def _take(f: _Field, wire: int, value: Any, got: dict[str, Any]) -> None:
    t = f.type
    if f.repeated and t == "int64":
        if wire == 0:
            got.setdefault(f.name, []).append(_signed(value))
            return
        if wire != 2:
            raise ProtoError(f"{f.name}: wire type {wire}")
        items = got.setdefault(f.name, [])
        q = 0
        while q < len(value):
            n, q = _read_varint(value, q)
            items.append(_signed(n))
        return
    want = {"int64": 0, "bool": 0, "double": 1}.get(t, 2)
    if wire != want:
        raise ProtoError(f"{f.name}: wire type {wire}, not {want}")
    if t == "int64":
        v: Any = _signed(value)
    elif t == "bool":
        v = bool(value)
    elif t == "double":
        v = _DOUBLE.unpack(value)[0]
    elif t == "string":
        try:
            v = bytes(value).decode("utf-8")
        except UnicodeDecodeError:
            raise ProtoError(f"{f.name}: not UTF-8") from None
    else:
        v = bytes(value)
    if f.repeated:
        got.setdefault(f.name, []).append(v)
    else:
        got[f.name] = v  # the last one wins, as in protobuf


def _not_a_number(constant: str) -> Any:
    raise ValueError(f"{constant} is not a JSON number")


def _with_extra(
    got: dict[str, Any], order_of: Callable[[dict[str, Any], dict[str, Any]], tuple[str, ...]]
) -> dict[str, Any]:
    """The members of the fields and of ``extra`` in the writers' order."""
    extra: dict[str, Any] = {}
    text = got.pop("extra", None)
    if text is not None:
        try:
            extra = json.loads(text, parse_constant=_not_a_number)
        except RecursionError:
            raise ProtoError("extra: not valid JSON: nested too deeply") from None
        except ValueError as exc:
            raise ProtoError(f"extra: not JSON ({exc})") from None
        if not isinstance(extra, dict):
            raise ProtoError("extra: not a JSON object")
    out: dict[str, Any] = {}
    for key in order_of(got, extra):
        if key in got:
            out[key] = got.pop(key)
        elif key in extra:
            out[key] = extra.pop(key)
    out.update(got)  # fields of the schema outside the order (none today)
    out.update(extra)
    return out


def decode_frame(data: bytes) -> dict[str, Any]:
    """A ``modbus.Frame`` message back to its format-2 ``/modbus/frames`` object."""
    got = _decode(messages()[FRAME_SCHEMA], data)
    if "pdu" in got:
        got["pdu"] = _hex_of(got["pdu"])
    chunk = got.pop("chunk", None)
    out = _with_extra(got, lambda got, extra: _FRAME_ORDER)
    if chunk is not None:  # format 4's marker of a left-out chunk: always the last member
        out.pop("chunk", None)  # (one in extra too would be damage: the field's wins)
        out["chunk"] = chunk
    return out


def decode_raw(data: bytes) -> dict[str, Any]:
    """A ``modbus.Raw`` message back to its format-2 ``/modbus/raw`` object."""
    got = _decode(messages()[RAW_SCHEMA], data)
    if "data" in got:
        got["data"] = base64.b64encode(got["data"]).decode("ascii")
    return _with_extra(got, _raw_order)


def _raw_order(got: dict[str, Any], extra: dict[str, Any]) -> tuple[str, ...]:
    kind = got.get("type", extra.get("type"))
    return _EVENT_ORDER if kind == "event" else _CHUNK_ORDER


#: topic -> the message its format-3 messages are
PROTO_NAMES = {"/modbus/frames": FRAME_SCHEMA, "/modbus/raw": RAW_SCHEMA}

#: schema name -> the decoder that gives its messages' format-2 objects
DECODERS: dict[str, Callable[[bytes], dict[str, Any]]] = {
    FRAME_SCHEMA: decode_frame,
    RAW_SCHEMA: decode_raw,
}


def decode_payload(schema_name: str, message_encoding: str, data: bytes) -> Any:
    """A message's object as mbmon's readers see it, from its channel's message encoding
    and schema name: a protobuf message of format 3 its format-2 object, JSON decoded."""
    if message_encoding == "protobuf":
        decoder = DECODERS.get(schema_name)
        if decoder is None:
            raise ProtoError(f"{schema_name} is not a protobuf schema mbmon reads")
        return decoder(data)
    return json.loads(data)
