"""JSON lines of records, fast: ``json_line(record_to_json(record, view))`` in UTF-8.

:mod:`mbmon.format` owns the JSON object of a record (:func:`~mbmon.format.record_to_json`,
keys documented in docs/json.md); this module owns writing it as a line quickly,
for ``read --json``, ``.jsonl``, MCAP and the compiled core alike.

A frame record's JSON differs from one record to the next only in its index, time,
transaction id, latency, request index and device notes; the rest is fixed by its
stream and direction (endpoints, label) or by its PDU, request PDU, kind, unit and
crc_ok, which polling repeats. Those fixed parts are cut once out of the full
encoding (:func:`_cache_json_parts`, which checks its work against it) when a PDU
is seen the second time and kept in the view's :class:`~mbmon.jsoncache.JsonLineCache`;
a record then only fills in its own values. ``tests/test_format.py`` compares every
line with the full encoding.
"""

from __future__ import annotations

from binascii import hexlify as _hexlify
from typing import Any

from mbmon.format import (
    DEFAULT_TIME,
    IDS_BYTES,
    IDS_NO_TID_BYTES,
    LATENCY_BYTES,
    LINE_BYTES,
    MAX_VALUES_SHOWN,
    NO_REQUEST_BYTES,
    View,
    generic_note,
    json_bytes,
    json_line,
    monitor_hex,
    record_to_json,
    values_text,
)
from mbmon.jsoncache import JsonLineCache
from mbmon.model import Direction, Frame, Pdu, Record, RecordKind, Stream
from mbmon.protocol.functions import FUNCTIONS, derived
from mbmon.stored import StoredRecord
from mbmon.timefmt import TimeFormat

#: Stands for a per-record value while the fixed parts of a JSON line are cut out.
_SENTINEL = "\x00mbmon: per-record value\x00"
_PER_RECORD = ("index", "time", "tid", "line", "notes", "latency_ms", "request_index")

_READS: set[int] = set()  # the reads, from the one function-code table


@derived
def _reads_from_table() -> None:
    _READS.clear()
    _READS.update(fc for fc, spec in FUNCTIONS.items() if spec.read)


_RESPONSE_KIND = RecordKind.RESPONSE
_S2C = Direction.S2C


def record_json_bytes(record: Record, view: View) -> bytes:
    """``json_line(record_to_json(record, view))`` in UTF-8, about 3x faster for frames.

    The fixed parts of a frame record's line are cut out of its full encoding when
    its PDU is seen the second time and kept in ``view.json_cache``; a record then
    only fills in its own values (an answer to a read whose values change every
    poll fills them into its request's template).
    Bytes, not text: the line holds non-ASCII text (labels), and building it from
    UTF-8 parts saves encoding about 900 characters per record on output.
    """
    frame = record.frame
    if frame is None:
        if type(record) is StoredRecord:  # a log's object: careful with what damage left
            return json_line(record.json(view.time_format)).encode()
        return json_bytes(record_to_json(record, view))
    cache = view.json_cache
    stream = frame.stream
    pdu = frame.pdu
    request = record.request
    req_pdu = request.pdu if request is not None else None
    head = cache.heads.get((stream.id, frame.direction))
    key = (id(pdu), id(req_pdu), record.kind, frame.unit, frame.crc_ok)
    parts = cache.parts.get(key)
    if parts is not None and parts[0] is pdu and parts[1] is req_pdu:
        if head is not None and head[0] is stream:
            return _json_from_parts(record, frame, head, parts, view.time_format)
    elif head is not None and head[0] is stream:
        if _has_read_template(record, pdu, req_pdu):
            template = cache.read_templates.get(
                (id(req_pdu), frame.unit, frame.crc_ok, pdu.fc, len(pdu.raw))
            )
            if template is None or template[0] is not req_pdu:
                return _cache_json_parts(record, view)  # makes the template
            if template[1] is not None:
                parts = _fill_read(template, pdu)
                if key in cache.seen_once:  # the same values again (polling a still robot)
                    cache.keep_parts(parts, record.kind, frame)
                else:
                    cache.seen(key)
                return _json_from_parts(record, frame, head, parts, view.time_format)
        if key not in cache.seen_once:
            cache.seen(key)
            return json_bytes(record_to_json(record, view))
    return _cache_json_parts(record, view)


def _has_read_template(record: Record, pdu: Pdu, req_pdu: Pdu | None) -> bool:
    """Whether a frame record is an answer that its read's template makes: a
    well-formed answer to a read, without fields (see ``JsonLineCache.read_templates``)."""
    return (
        req_pdu is not None
        and record.kind is _RESPONSE_KIND
        and pdu.fc in _READS
        and not pdu.malformed
        and not pdu.fields
    )


def _fill_read(template: tuple[Any, ...], pdu: Pdu) -> tuple[Any, ...]:
    """The fixed JSON parts (as ``JsonLineCache.parts`` holds them) of an answer to a
    read, from its request's template and its own values: what
    :func:`_parts_from_json` gives, without building and encoding the record's JSON
    object and generic note."""
    req_pdu, to_values, note_head, to_latency, to_index, end, bits = template
    values = pdu.values or ()
    hex_text = _hexlify(pdu.raw, b" ").upper()
    values_json = json_bytes(values)  # a tuple encodes as the list record_to_json has
    if bits or len(values) > MAX_VALUES_SHOWN:
        shown = values_text(values, bits).encode()
    else:  # registers in decimal: the JSON list's items, as values_text joins them
        shown = values_json[1:-1].replace(b",", b", ")
    note = b'%b%b"' % (note_head, shown)
    return (
        pdu,
        req_pdu,
        b'%b%b,"pdu":"%b","line":' % (to_values, values_json, hex_text),
        hex_text,
        note,
        note[1:-1],
        to_latency,
        to_index,
        end,
    )


def _keep_read_template(cache: JsonLineCache, parts: tuple[Any, ...], frame: Frame) -> None:
    """Cut the template of answers to ``parts``' request out of one answer's checked
    parts (see ``JsonLineCache.read_templates``); an answer whose parts do not have
    the values where the template expects them leaves none (its request's answers
    then take the general path)."""
    pdu, req_pdu, to_line, _, note_json, _, to_latency, to_index, end = parts
    spec = FUNCTIONS.get(pdu.fc)
    bits = spec is not None and spec.bits
    # this answer's own pieces, as _fill_read makes them: filled into a template
    # with nothing around them, its text from "values" on and its note's values
    mine = _fill_read((req_pdu, b',"values":', b"", to_latency, to_index, end, bits), pdu)
    tail, shown = mine[2], mine[4]
    template: tuple[Any, ...] = (req_pdu, None)
    if to_line.endswith(tail) and note_json.endswith(shown):
        template = (
            req_pdu,
            to_line[: len(to_line) - len(tail)] + b',"values":',
            note_json[: len(note_json) - len(shown)],
            to_latency,
            to_index,
            end,
            bits,
        )
        if _fill_read(template, pdu) != parts:
            template = (req_pdu, None)  # none for this request: not tried again
    cache.keep_template((id(req_pdu), frame.unit, frame.crc_ok, pdu.fc, len(pdu.raw)), template)


def _json_from_parts(
    record: Record,
    frame: Frame,
    head: tuple[Stream, bytes, bytes],
    parts: tuple[Any, ...],
    time_format: TimeFormat,
) -> bytes:
    """A frame record's JSON line from its cached fixed parts and its own values."""
    return frame_json_bytes(
        record.index,
        record.ts,
        frame.unit,
        frame.tid,
        head,
        parts,
        record.latency,
        record.request_index,
        record.request is None and frame.direction is _S2C,
        record.notes,
        time_format,
    )


def frame_json_bytes(
    index: int,
    ts: float,
    unit: int,
    tid: int | None,
    head: tuple[Stream, bytes, bytes],
    parts: tuple[Any, ...],
    latency: float | None,
    request_index: int | None,
    unmatched_response: bool,
    notes: tuple[str, ...] = (),
    time_format: TimeFormat = DEFAULT_TIME,
) -> bytes:
    """The JSON line of a frame record from its values and its cached fixed parts.

    ``head`` and ``parts`` are what :func:`record_json_bytes` cached for the record's
    stream direction and PDU; ``unmatched_response`` is a response without a request
    (its line says so). The one place that lays out a frame record's line, for
    :func:`record_json_bytes`.
    """
    _, _, to_line, hex_text, note_json, note_escaped, to_latency, to_index, end = parts
    if notes:  # device notes vary with state: encoded per record
        encoded = [json_bytes(note) for note in notes]
        note_json += b"," + b",".join(encoded)
        note_escaped += b"; " + b"; ".join(text[1:-1] for text in encoded)
    if latency is not None:  # as format's latency text
        note_escaped += LATENCY_BYTES % (latency * 1000)
        latency_json = json_bytes(round(latency * 1000, 3))
    else:
        latency_json = b"null"
        if unmatched_response:
            note_escaped += NO_REQUEST_BYTES
    if tid is None:
        ids, tid_json = IDS_NO_TID_BYTES % unit, b"null"
    else:
        ids, tid_json = IDS_BYTES % (unit, tid), b"%d" % tid
    line = LINE_BYTES % (time_format.bytes(ts), head[2], ids, hex_text, note_escaped)
    return b'{"index":%d,"time":%b%b%b%b"%b","notes":[%b]%b%b%b%b%b' % (
        index,
        json_bytes(ts),
        head[1],
        tid_json,
        to_line,
        line,
        note_json,
        to_latency,
        latency_json,
        to_index,
        b"null" if request_index is None else b"%d" % request_index,
        end,
    )


#: The PDU-dependent JSON keys of a frame record between "tid" and "line", and
#: after "notes", in record_to_json's order; their texts (``,"key":``) are checked
#: once against a full encoding before :func:`_parts_from_json` may use them.
_TO_LINE_KEYS = ("unit", "fc", "kind", "exception_code", "address", "count", "values", "pdu")
_KEY_TEXT = {
    k: b',"%b":' % k.encode()
    for k in (*_TO_LINE_KEYS, "line", "crc_ok", "latency_ms", "malformed", "request_index")
}


def _parts_from_json(obj: dict[str, Any], pdu: Pdu, req_pdu: Pdu | None) -> tuple[Any, ...]:
    """A frame record's fixed JSON parts (see ``JsonLineCache.parts``) from its
    :func:`~mbmon.format.record_to_json` object, each value encoded on its own: what
    the full encoding cut at the per-record values gives, without encoding the
    whole object twice and cutting it (a PDU whose values change every poll
    is seen once; its parts are made here)."""
    j = json_bytes
    k = _KEY_TEXT
    to_line = b"".join([b"%b%b" % (k[key], j(obj[key])) for key in _TO_LINE_KEYS]) + k["line"]
    note_json = j(obj["notes"][0])
    return (
        pdu,
        req_pdu,
        to_line,
        obj["pdu"].encode(),
        note_json,
        note_json[1:-1],
        k["crc_ok"] + j(obj["crc_ok"]) + k["latency_ms"],
        k["malformed"] + j(obj["malformed"]) + k["request_index"],
        b"}",
    )


def _cache_json_parts(record: Record, view: View) -> bytes:
    """``record``'s JSON line, encoded in full; its fixed parts are cut out of it and
    cached when they give it back (a note that held the sentinel would not).

    Once the stream direction's head is cached and the key texts are confirmed,
    a PDU without ``fields`` takes :func:`_parts_from_json` instead: the same
    parts from the record's JSON object, value by value."""
    frame = record.frame
    assert frame is not None
    cache = view.json_cache
    stream, pdu = frame.stream, frame.pdu
    req_pdu = record.request.pdu if record.request is not None else None
    head = cache.heads.get((stream.id, frame.direction))
    if cache.keys_checked and head is not None and head[0] is stream and not pdu.fields:
        parts = _parts_from_json(record_to_json(record, view, line=False), pdu, req_pdu)
        _keep(cache, record, parts, frame)
        return _json_from_parts(record, frame, head, parts, view.time_format)
    obj = record_to_json(record, view)
    full = json_bytes(obj)
    original = dict(obj)
    for key in _PER_RECORD:
        obj[key] = _SENTINEL
    pieces = json_bytes(obj).split(json_bytes(_SENTINEL))
    if len(pieces) != len(_PER_RECORD) + 1 or pieces[:2] != [b'{"index":', b',"time":']:
        return full
    _, _, head_text, to_line, notes_key, to_latency, to_index, end = pieces
    if notes_key != b',"notes":':
        return full
    note_json = json_bytes(generic_note(pdu, req_pdu))
    label_escaped = json_bytes(view.label(stream, frame.direction))[1:-1]
    head = (stream, head_text, label_escaped)
    parts = (
        pdu,
        req_pdu,
        to_line,
        monitor_hex(pdu.raw).encode(),
        note_json,
        note_json[1:-1],
        to_latency,
        to_index,
        end,
    )
    if _json_from_parts(record, frame, head, parts, view.time_format) != full:
        return full
    if not cache.keys_checked and "fields" not in original:
        if _parts_from_json(original, pdu, req_pdu) == parts:
            cache.keys_checked = True
    cache.keep_head((stream.id, frame.direction), head)
    _keep(cache, record, parts, frame)
    return full


def _keep(cache: JsonLineCache, record: Record, parts: tuple[Any, ...], frame: Frame) -> None:
    """Cache a frame record's checked parts, and the read template of a well-formed
    answer to a read."""
    cache.keep_parts(parts, record.kind, frame)
    if _has_read_template(record, frame.pdu, parts[1]):
        _keep_read_template(cache, parts, frame)
