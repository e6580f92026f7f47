"""Text of records: the robot's monitor lines (manual Table 57), labels, generic notes, JSON.

This module owns every human-readable string mbmon prints about traffic and the
stable JSON object of ``read --json``. Events carry no text; this turns them
into text, for the console and for every sink alike.

The monitor line is the PDU only (function code + data), upper-case hex, single
spaces: no unit id, no MBAP header, no CRC (manual §5.5, Table 57).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from mbmon.jsoncache import JsonLineCache
from mbmon.model import (
    Direction,
    EventKind,
    Frame,
    Kind,
    Pdu,
    Record,
    RecordKind,
    Stream,
    Transport,
)
from mbmon.protocol.functions import FUNCTIONS
from mbmon.stored import StoredRecord
from mbmon.timefmt import TimeFormat

#: Function code names (Modbus Application Protocol v1.1b); kept here so that
#: formatting never depends on the decoder's import graph.
_FC_NAMES: dict[int, str] | None = None
_EXC_NAMES: dict[int, str] | None = None

MAX_VALUES_SHOWN = 16
_MAX_NOISE_HEX = 32


def _names() -> tuple[dict[int, str], dict[int, str]]:
    global _FC_NAMES, _EXC_NAMES
    if _FC_NAMES is None or _EXC_NAMES is None:
        from mbmon.protocol.pdu import EXCEPTION_NAMES, FUNCTION_NAMES

        _FC_NAMES, _EXC_NAMES = FUNCTION_NAMES, EXCEPTION_NAMES
    return _FC_NAMES, _EXC_NAMES


#: The function-code table's entry for a code (:mod:`mbmon.protocol.functions`).
_function = FUNCTIONS.get


def function_name(fc: int) -> str:
    """Public name of a function code, or ``Function 0xNN`` for user-defined/unknown codes."""
    return _names()[0].get(fc) or f"Function 0x{fc:02X}"


def exception_name(code: int) -> str:
    return _names()[1].get(code) or f"Exception 0x{code:02X}"


_S2C = Direction.S2C
_HEX_CACHE: dict[bytes, str] = {}
_NOTE_CACHE: dict[tuple[bytes, Kind, bytes | None], str] = {}
_CACHE_SIZE = 8192
#: characters (or bytes) each text cache may hold before it is emptied: caches are
#: bounded in bytes, not only in entries (register answers make long texts)
_CACHE_CHARS = 1 << 20
_held = {"hex": 0, "note": 0}


def monitor_hex(raw: bytes) -> str:
    """PDU bytes as the robot's Modbus Monitor shows them: ``02 01 2C 00 05``."""
    text = _HEX_CACHE.get(raw)
    if text is None:
        if len(_HEX_CACHE) >= _CACHE_SIZE or _held["hex"] > _CACHE_CHARS:
            _HEX_CACHE.clear()
            _held["hex"] = 0
        text = _HEX_CACHE[raw] = raw.hex(" ").upper()
        _held["hex"] += len(text)
    return text


#: the default time format (``-t a`` without the automatic date): :func:`format_time`
DEFAULT_TIME = TimeFormat(auto_date=False)
#: its per-second cache: [second, "HH:MM:SS." text, the same in UTF-8]
_last_second: list[Any] = DEFAULT_TIME._second


def format_time(ts: float) -> str:
    """Time of day in local time with microseconds, like tcpdump (any float prints:
    see :mod:`mbmon.timefmt`; a view's own format is ``view.time_format``)."""
    return DEFAULT_TIME.text(ts)


def _time_bytes(ts: float) -> bytes:
    """``format_time(ts)`` in UTF-8."""
    return DEFAULT_TIME.bytes(ts)


# --------------------------------------------------------------------------- labels


def _host(endpoint: str) -> str:
    if endpoint.startswith("["):
        return endpoint[1 : endpoint.find("]")]
    return endpoint.rsplit(":", 1)[0] if endpoint.count(":") == 1 else endpoint


@dataclass(frozen=True, slots=True)
class View:
    """Whose eyes the labels are written for.

    ``robot=None`` gives neutral labels (``client → server`` with endpoints).
    ``robot="HOST[:PORT]"`` renders the robot's own Modbus Monitor labels:
    "Receive from client"/"Send to client" when the robot is the server,
    "Send to server"/"Receive from server" when it is the client. For RTU the
    robot is named by the bus name (``--robot /dev/ttyUSB0``) and is taken to
    be the server unless ``robot_is_client``.
    """

    robot: str | None = None
    robot_is_client: bool = False
    #: how times print (``-t``); each view has its own (it remembers the first day)
    time_format: TimeFormat = field(default_factory=TimeFormat, compare=False)
    #: the robot's peers seen so far (client endpoints when it serves, servers when it
    #: asks), up to two: with several, the robot's labels name the peer
    _peers: set[str] = field(default_factory=set, compare=False, repr=False)
    _labels: dict[tuple[int, Direction], tuple[Stream, str]] = field(
        default_factory=dict, compare=False, repr=False
    )
    #: the fixed parts of this view's JSON lines (:mod:`mbmon.jsonfmt` fills it)
    json_cache: JsonLineCache = field(default_factory=JsonLineCache, compare=False, repr=False)

    def robot_role(self, stream: Stream | None) -> str | None:
        """``"server"``, ``"client"`` or ``None`` (the robot is not on this stream)."""
        if self.robot is None or stream is None:
            return None
        if stream.transport is Transport.RTU:
            name = self.robot.rstrip("/").rsplit("/", 1)[-1]
            if self.robot == stream.server or name == stream.server.rsplit("/", 1)[-1]:
                return "client" if self.robot_is_client else "server"
            return None
        for role, endpoint in (("server", stream.server), ("client", stream.client)):
            if self.robot == endpoint:
                return role
            spec_has_port = (self.robot.startswith("[") and "]:" in self.robot) or (
                not self.robot.startswith("[") and self.robot.count(":") == 1
            )
            if not spec_has_port and self.robot.strip("[]") == _host(endpoint):
                return role
        return None

    def label(self, stream: Stream | None, direction: Direction) -> str:
        """The label of one direction of a stream (cached per stream: it is per-record work)."""
        if stream is None:
            return ""
        key = (stream.id, direction)
        hit = self._labels.get(key)
        if hit is not None and hit[0] is stream:
            return hit[1]
        text = self._label(stream, direction)
        if len(self._labels) > 65536:
            self._labels.clear()
        self._labels[key] = (stream, text)
        return text

    def _label(self, stream: Stream, direction: Direction) -> str:
        role = self.robot_role(stream)
        if role is None:
            if stream.transport is Transport.RTU:
                return "master → slave" if direction is Direction.C2S else "slave → master"
            return f"{stream.src(direction)} → {stream.dst(direction)}"
        if role == "server":
            text = "Receive from client" if direction is Direction.C2S else "Send to client"
        else:
            text = "Send to server" if direction is Direction.C2S else "Receive from server"
        if stream.transport is Transport.RTU:
            return text  # one bus, one master: nobody to tell apart
        peer = stream.client if role == "server" else stream.server
        peers = self._peers
        if len(peers) < 2 and peer not in peers:
            peers.add(peer)
            if len(peers) == 2:
                # a second peer: from now on every label names its peer (the cached
                # labels and JSON heads were made without)
                self._labels.clear()
                self.json_cache.heads.clear()
        return f"{text} {peer}" if len(peers) > 1 else text


# --------------------------------------------------------------------------- generic notes


def _range(address: int, count: int | None) -> str:
    if not count or count == 1:
        return str(address)
    return f"{address}..{address + count - 1}"


def values_text(values: tuple[int, ...] | None, bits: bool) -> str:
    if not values:
        return ""
    if bits:
        shown = "".join(["1" if v else "0" for v in values[:64]])
        return shown + ("…" if len(values) > 64 else "")
    text = ", ".join(map(str, values[:MAX_VALUES_SHOWN]))
    return text + (f", … ({len(values)} values)" if len(values) > MAX_VALUES_SHOWN else "")


def generic_note(pdu: Pdu, request: Pdu | None = None) -> str:
    """Short protocol-level meaning of one PDU: name, address range, values in decimal.

    A response is read with its request (``request``) for the address of a read.
    The text depends only on the two PDUs' bytes, so repeats (polling) are cached.
    """
    key = (pdu.raw, pdu.kind, request.raw if request is not None else None)
    text = _NOTE_CACHE.get(key)
    if text is None:
        if len(_NOTE_CACHE) >= _CACHE_SIZE or _held["note"] > _CACHE_CHARS:
            _NOTE_CACHE.clear()
            _held["note"] = 0
        text = _NOTE_CACHE[key] = _generic_note(pdu, request)
        _held["note"] += len(text)
    return text


def _generic_note(pdu: Pdu, request: Pdu | None) -> str:
    if pdu.kind is Kind.EXCEPTION:
        code = pdu.exception_code if pdu.exception_code is not None else 0
        return f"Exception {code:02X} {exception_name(code)} ({function_name(pdu.fc)})"
    name = function_name(pdu.fc)
    fc = pdu.fc
    spec = _function(fc)
    bits = spec is not None and spec.bits
    address = pdu.address
    count = pdu.count
    if pdu.kind is Kind.RESPONSE and spec is not None and spec.read and request is not None:
        address, count = request.address, request.count
    parts = [name]
    if fc == 8 and "sub_function" in pdu.fields:
        parts.append(_diagnostic_text(pdu.fields["sub_function"]))
    elif fc == 0x2B and "mei_type" in pdu.fields:
        parts = [_mei_text(pdu)]
    elif address is not None:
        parts.append(_range(address, count))
    elif count is not None:
        parts.append(f"count {count}")
    text = " ".join(parts)
    shape = spec.shape if spec is not None else None
    if shape == "mask_write" and "and_mask" in pdu.fields and "or_mask" in pdu.fields:
        text += f" and=0x{pdu.fields['and_mask']:04X} or=0x{pdu.fields['or_mask']:04X}"
    if shape == "read_write" and pdu.kind is Kind.REQUEST and "write_address" in pdu.fields:
        text += f", write {_range(pdu.fields['write_address'], pdu.fields.get('write_count'))}"
        written = values_text(pdu.fields.get("write_values"), False)
        if written:
            text += f" = {written}"
    shown = values_text(pdu.values, bits)
    if bits and shape == "write_single" and pdu.values:
        shown = "ON" if pdu.values[0] else "OFF"
    if shown:
        text += f" = {shown}"
    if fc == 0x2B and "objects" in pdu.fields:
        objects = pdu.fields["objects"]
        text += ": " + ", ".join(f"{_mei_object(oid)}={val!r}" for oid, val in objects)
    if pdu.malformed:
        text += f" [malformed: {pdu.malformed}]"
    return text


def _diagnostic_text(sub: int) -> str:
    """``sub-function 4 Force Listen Only Mode``: a Diagnostics sub-function by number and name."""
    from mbmon.protocol.pdu import DIAGNOSTIC_NAMES

    name = DIAGNOSTIC_NAMES.get(sub)
    return f"sub-function {sub} {name}" if name else f"sub-function {sub}"


def _mei_text(pdu: Pdu) -> str:
    """An MEI transport (0x2B) by its MEI type's name: ``Read Device Identification basic,
    object 0 VendorName`` (request) or ``... basic, 3 objects`` (response)."""
    from mbmon.protocol.pdu import MEI_TYPE_NAMES, READ_DEVICE_ID_NAMES

    fields = pdu.fields
    mei = fields["mei_type"]
    name = MEI_TYPE_NAMES.get(mei)
    if name is None:
        return f"{function_name(pdu.fc)} MEI type 0x{mei:02X}"
    text = name
    code = fields.get("read_device_id_code")
    if code is not None:
        text += " " + READ_DEVICE_ID_NAMES.get(code, f"code {code}")
    if pdu.kind is Kind.REQUEST and "object_id" in fields:
        oid = fields["object_id"]
        named = _mei_object(oid)
        text += f", object {oid}" + (f" {named}" if named != str(oid) else "")
    return text


def _mei_object(oid: int) -> str:
    """A device identification object's name (``VendorName``), or its number."""
    from mbmon.protocol.pdu import MEI_OBJECT_NAMES

    return MEI_OBJECT_NAMES.get(oid, str(oid))


def frame_notes(record: Record) -> tuple[str, ...]:
    """Generic note first, then the annotator's notes."""
    frame = record.frame
    if frame is None:
        return record.notes
    request = record.request.pdu if record.request is not None else None
    return (generic_note(frame.pdu, request), *record.notes)


# --------------------------------------------------------------------------- lines


def _event_text(record: Record, view: View) -> str:
    event = record.event
    assert event is not None
    stream = event.stream
    info = event.info
    role = view.robot_role(stream)
    if event.kind is EventKind.CONNECT and stream is not None:
        if role == "server":
            return f"Client {stream.client} connected"
        if role == "client":
            return f"Connected to server {stream.server}"
        return f"Connect {stream.client} → {stream.server} ({stream.transport.value})"
    if event.kind is EventKind.DISCONNECT and stream is not None:
        how = info.get("how", "fin")
        by = info.get("by")
        tail = f" ({how.upper()}{' by ' + by if by else ''})"
        if role == "server":
            return f"Client {stream.client} disconnected{tail}"
        if role == "client":
            return f"Disconnected from server {stream.server}{tail}"
        return f"Disconnect {stream.client} → {stream.server}{tail}"
    if event.kind is EventKind.GAP:
        return f"Gap: {info.get('bytes', '?')} bytes missing ({info.get('direction', '?')})"
    if event.kind is EventKind.TIMEOUT:
        fc = info.get("fc")
        what = function_name(fc) if isinstance(fc, int) else "request"
        idx = info.get("request_index")
        return f"No response to {what}" + (f" (record #{idx})" if idx is not None else "")
    if event.kind is EventKind.ERROR:
        return f"Error: {info.get('message', '')}"
    if event.kind is EventKind.NOTICE:
        return f"Notice: {info.get('message', '')}"
    if event.kind is EventKind.GUARD:
        return f"Guard: {info.get('message', '')}"
    if event.kind is EventKind.STATS:
        return "Stats: " + ", ".join(f"{k}={v}" for k, v in info.items())
    return event.kind.value


#: The monitor line of a frame (time, label, [uUNIT tTID], PDU hex, notes) and its
#: parts, as %-formats: the same texts also make the line in UTF-8 (``*_BYTES``, for
#: :func:`record_json_bytes`, JSON-escaped piece by piece: escaping the pieces
#: escapes the whole).
_LINE = "%s  %s  [%s]  %s  | %s"
_IDS = "u%d t%d"  # unit, transaction id
_IDS_NO_TID = "u%d"  # unit (RTU)
_LATENCY = " (%.1f ms)"  # a response's latency in ms
_NO_REQUEST = " (no matching request)"  # a response that nothing asked for
LINE_BYTES, IDS_BYTES, IDS_NO_TID_BYTES, LATENCY_BYTES, NO_REQUEST_BYTES = (
    text.replace("%s", "%b").encode() for text in (_LINE, _IDS, _IDS_NO_TID, _LATENCY, _NO_REQUEST)
)


def _ids(frame: Frame) -> str:
    tid = frame.tid
    return _IDS % (frame.unit, tid) if tid is not None else _IDS_NO_TID % frame.unit


def _latency_text(record: Record, frame: Frame) -> str:
    """The end of a frame's line: the latency of a response, or why it has none."""
    latency = record.latency
    if latency is not None:
        return _LATENCY % (latency * 1000) if frame.stream.timed else ""
    if record.request is None and frame.direction is _S2C:
        return _NO_REQUEST
    return ""


def record_line(record: Record, view: View, notes: tuple[str, ...] | None = None) -> str:
    """The full console/text line of a record: time, label, monitor hex, notes (plain text).

    ``notes`` are the record's :func:`frame_notes` when the caller has them already.
    """
    stream = record.stream
    if stream is None or stream.timed:
        when = view.time_format.text(record.ts)
    else:  # no capture times (a raw RTU dump): the record number instead
        when = "#%d" % record.index  # noqa: UP031
    kind = record.kind
    if record.frame is not None:
        frame = record.frame
        if notes is None:
            notes = frame_notes(record)
        return _LINE % (
            when,
            view.label(frame.stream, frame.direction),
            _ids(frame),
            monitor_hex(frame.pdu.raw),
            "; ".join(notes) + _latency_text(record, frame),
        )
    if type(record) is StoredRecord:  # read back from a log: its line, as recorded
        return record.text(view.time_format)
    if kind is RecordKind.NOISE and record.noise is not None:
        noise = record.noise
        shown = monitor_hex(noise.raw[:_MAX_NOISE_HEX]) + (
            " …" if len(noise.raw) > _MAX_NOISE_HEX else ""
        )
        if noise.direction is Direction.BUS:
            where = noise.stream.server
        else:
            where = view.label(noise.stream, noise.direction)
        return f"{when}  {where}  !! noise, {len(noise.raw)} bytes ({noise.reason}): {shown}"
    if kind is RecordKind.EVENT and record.event is not None:
        return f"{when}  -- {_event_text(record, view)}"
    if kind is RecordKind.COMMAND and record.command is not None:
        cmd = record.command
        dur = (
            f" after {cmd.duration:.3f} s" if cmd.duration is not None and cmd.stream.timed else ""
        )
        return f"{when}  >> [{cmd.phase.value}{dur}] unit {cmd.unit}: {cmd.text}"
    return f"{when}  ?"


# --------------------------------------------------------------------------- JSON

_JSON_KEYS = (
    "index", "time", "stream", "src", "dst", "transport", "tid", "unit", "fc", "kind",
    "exception_code", "address", "count", "values", "pdu", "line", "notes", "crc_ok",
    "latency_ms", "malformed", "request_index",
)  # fmt: skip


def _jsonable(value: Any) -> Any:
    if isinstance(value, bytes | bytearray):
        return value.hex()
    if isinstance(value, tuple | list):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict) or hasattr(value, "items"):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if hasattr(value, "value") and not isinstance(value, int | float | str | bool):
        return value.value
    return value


def finite(value: Any) -> Any:
    """``value`` with NaN/inf (not JSON) replaced by None, recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value


def _careful_line(obj: Any) -> str:
    """:func:`json_line` of what orjson refuses (a record read from a damaged log): an
    integer beyond 64 bits stays exact, NaN/inf become null, a string with a lone
    surrogate is escaped (``\\udcff``), keys and other values become strings."""
    import json

    clean = finite(obj)
    text = json.dumps(clean, ensure_ascii=False, separators=(",", ":"), default=str)
    try:
        text.encode()
    except UnicodeEncodeError:
        text = json.dumps(clean, separators=(",", ":"), default=str)
    return text


try:  # orjson is several times faster than the standard encoder on the hot path
    import orjson as _orjson

    def json_line(obj: dict[str, Any]) -> str:
        """One JSON record as a compact line (no trailing newline), non-ASCII kept."""
        try:
            return _orjson.dumps(obj).decode()
        except TypeError:  # orjson.JSONEncodeError: see _careful_line
            return _careful_line(obj)

    #: json_line(obj) in UTF-8
    json_bytes: Callable[[Any], bytes] = _orjson.dumps

except ImportError:  # pragma: no cover - orjson is a dependency; keep working without it
    import json as _json

    _encode = _json.JSONEncoder(ensure_ascii=False, separators=(",", ":")).encode

    def json_line(obj: dict[str, Any]) -> str:
        """One JSON record as a compact line (no trailing newline), non-ASCII kept."""
        return _encode(obj)

    def _standard_bytes(obj: Any) -> bytes:
        return _encode(obj).encode()

    json_bytes = _standard_bytes


#: enum member -> its plain str value (orjson serialises a plain str several times
#: faster than a str-enum member, and ``.value`` is a slow descriptor)
_PLAIN: dict[Any, str] = {m: str(m.value) for e in (RecordKind, Transport) for m in e}


def record_to_json(record: Record, view: View, *, line: bool = True) -> dict[str, Any]:
    """The stable JSON object of ``read --json`` (keys documented in docs/json.md).

    ``line=False`` leaves a frame record's "line" ``None``, for callers that lay
    the line out themselves (:func:`_cache_json_parts`)."""
    frame: Frame | None = record.frame
    if frame is not None:  # the hot path: one dict literal, keys in documented order
        pdu = frame.pdu
        stream = frame.stream
        if frame.direction is _S2C:
            src, dst = stream.server, stream.client
        else:
            src, dst = stream.client, stream.server
        address, count = pdu.address, pdu.count
        request = record.request
        if address is None and request is not None and pdu.kind is not Kind.REQUEST:
            address, count = request.pdu.address, request.pdu.count
        notes = frame_notes(record)
        latency = record.latency
        values = pdu.values
        timed = stream.timed
        if not timed:
            latency = None
        obj: dict[str, Any] = {
            "index": record.index,
            "time": record.ts if timed else None,
            "stream": stream.id,
            "src": src,
            "dst": dst,
            "transport": _PLAIN[stream.transport],
            "tid": frame.tid,
            "unit": frame.unit,
            "fc": pdu.fc,
            "kind": _PLAIN[record.kind],
            "exception_code": pdu.exception_code,
            "address": address,
            "count": count,
            "values": list(values) if values is not None else None,
            "pdu": monitor_hex(pdu.raw),
            "line": record_line(record, view, notes) if line else None,
            "notes": list(notes),
            "crc_ok": frame.crc_ok,
            "latency_ms": round(latency * 1000, 3) if latency is not None else None,
            "malformed": pdu.malformed,
            "request_index": record.request_index,
        }
        if pdu.fields:
            obj["fields"] = _jsonable(pdu.fields)
        return obj
    if type(record) is StoredRecord:  # read back from a log: its object, as recorded
        return record.json(view.time_format)
    out: dict[str, Any] = dict.fromkeys(_JSON_KEYS)
    out["index"] = record.index
    out["time"] = record.ts if record.stream is None or record.stream.timed else None
    out["kind"] = record.kind.value
    if record.stream is not None:
        out["stream"] = record.stream.id
        out["transport"] = record.stream.transport.value
    out["line"] = record_line(record, view)
    if record.noise is not None:
        noise = record.noise
        out["src"] = noise.stream.src(noise.direction)
        out["dst"] = noise.stream.dst(noise.direction)
        out["pdu"] = monitor_hex(noise.raw)
        out["malformed"] = noise.reason
        out["notes"] = [f"noise, {len(noise.raw)} bytes ({noise.reason})"]
    elif record.event is not None:
        event = record.event
        out["event"] = event.kind.value
        out["info"] = _jsonable(dict(event.info))
        if event.stream is not None:
            out["src"] = event.stream.client
            out["dst"] = event.stream.server
        out["notes"] = [_event_text(record, view)]
    elif record.command is not None:
        cmd = record.command
        out["unit"] = cmd.unit
        out["src"] = cmd.stream.client
        out["dst"] = cmd.stream.server
        out["command"] = {
            "phase": cmd.phase.value,
            "text": cmd.text,
            "code": cmd.code,
            "duration": cmd.duration,
            "params": _jsonable(dict(cmd.params)),
        }
        out["notes"] = [cmd.text]
    return out
