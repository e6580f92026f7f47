"""Field decoders of the functions whose layout is their own (no table ``shape``).

Serial-line diagnostics and counters (07, 08, 0B, 0C, 11), file records (14,
15) and the encapsulated interface (2B, Read Device Identification). ``BY_CODE``
maps each code to its request and response decoders, the FIFO queue (18,
:mod:`mbmon.protocol.fields_access`) included. Pure.
"""

from __future__ import annotations

from typing import Any, Final

from mbmon.model import Pdu
from mbmon.protocol.fields import Decoder, Out, paired_request, u16, unpack_words
from mbmon.protocol.fields_access import FIFO

__all__ = ["BY_CODE"]


def _empty_req(o: Out, request: Pdu | None) -> None:
    o.fixed(1)


def _exc_status_resp(o: Out, request: Pdu | None) -> None:
    o.fixed(2)
    if len(o.d) >= 2:
        o.fields["status"] = o.d[1]


def _diagnostics(o: Out, request: Pdu | None) -> None:
    d = o.d
    if not o.need(3):
        return
    sub = (d[1] << 8) | d[2]
    data = d[3:]
    o.fields["sub_function"] = sub
    o.fields["data"] = data
    if len(data) % 2 == 0:
        o.values = unpack_words(data)
    if sub == 0x00:
        req = paired_request(request, 0x08)
        if req is not None and req.fields.get("sub_function") == 0 and req.raw != d:
            o.bad.append("echo differs from request")
    elif not (sub == 0x15 and o.role == "response"):
        o.fixed(5)


def _event_counter_resp(o: Out, request: Pdu | None) -> None:
    o.fixed(5)
    status, events = u16(o.d, 1), u16(o.d, 3)
    if status is not None:
        o.fields["status"] = status
    if events is not None:
        o.fields["event_count"] = events


def _event_log_resp(o: Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    if (o.byte_count or 0) < 6:
        o.bad.append(f"byte count {o.byte_count} below 6")
    for name, i in (("status", 0), ("event_count", 2), ("message_count", 4)):
        v = u16(data, i)
        if v is not None:
            o.fields[name] = v
    o.fields["events"] = data[6:]


def _server_id_resp(o: Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    o.fields["server_id"] = data[:-1]
    if data:
        o.fields["run_indicator"] = data[-1]


def _file_check(o: Out, rec: dict[str, Any]) -> None:
    if rec["reference_type"] != 6:
        o.bad.append(f"reference type {rec['reference_type']} is not 6")
    if rec.get("record_number", 0) > 9999:
        o.bad.append(f"record number {rec['record_number']} exceeds 9999")


def _file_header(d: bytes, i: int) -> dict[str, Any]:
    return {
        "reference_type": d[i],
        "file_number": (d[i + 1] << 8) | d[i + 2],
        "record_number": (d[i + 3] << 8) | d[i + 4],
        "record_length": (d[i + 5] << 8) | d[i + 6],
    }


def _read_file_req(o: Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    bc = o.byte_count or 0
    if not 0x07 <= bc <= 0xF5:
        o.bad.append(f"byte count {bc} outside 7..245")
    if bc % 7:
        o.bad.append(f"byte count {bc} is not a multiple of 7")
    records = []
    for i in range(0, len(data) - 6, 7):
        rec = _file_header(data, i)
        _file_check(o, rec)
        records.append(rec)
    o.fields["records"] = tuple(records)


def _read_file_resp(o: Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    if o.byte_count == 0:  # as the request (7..245) and both 0x15 frames (9..251)
        o.bad.append("byte count 0")
    records: list[dict[str, Any]] = []
    i = 0
    while i < len(data):
        length = data[i]
        if length < 1:
            o.bad.append(f"sub-response {len(records) + 1} has length 0")
            break
        if i + 1 + length > len(data):
            o.bad.append(f"sub-response {len(records) + 1} truncated")
            break
        words = data[i + 2 : i + 1 + length]
        if len(words) % 2:
            o.bad.append(f"sub-response {len(records) + 1} has odd data length {len(words)}")
        rec: dict[str, Any] = {"reference_type": data[i + 1]}
        rec["record_length"] = len(words) // 2
        rec["data"] = unpack_words(words)
        _file_check(o, rec)
        records.append(rec)
        i += 1 + length
    req = paired_request(request, 0x14)
    asked = req.fields.get("records") if req is not None else None
    if asked is not None and len(asked) == len(records):
        for rec, ask in zip(records, asked, strict=True):
            rec["file_number"] = ask["file_number"]
            rec["record_number"] = ask["record_number"]
            if ask["record_length"] != rec["record_length"]:
                o.bad.append(
                    f"record of {rec['record_length']} words but {ask['record_length']} requested"
                )
    o.fields["records"] = tuple(records)


def _write_file(o: Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    bc = o.byte_count or 0
    if not 0x09 <= bc <= 0xFB:
        o.bad.append(f"byte count {bc} outside 9..251")
    records: list[dict[str, Any]] = []
    i = 0
    while i < len(data):
        if i + 7 > len(data):
            o.bad.append(f"sub-request {len(records) + 1} truncated")
            break
        rec = _file_header(data, i)
        end = i + 7 + 2 * rec["record_length"]
        if end > len(data):
            o.bad.append(f"sub-request {len(records) + 1} truncated")
        rec["data"] = unpack_words(data[i + 7 : end])
        _file_check(o, rec)
        records.append(rec)
        i = end
    o.fields["records"] = tuple(records)
    req = paired_request(request, 0x15)
    if o.role == "response" and req is not None and req.raw != o.d:
        o.bad.append("echo differs from request")


def _text(b: bytes) -> str:
    try:
        return b.decode("utf-8")
    except UnicodeDecodeError:
        return b.decode("latin-1")


def _mei(o: Out, request: Pdu | None) -> None:
    d = o.d
    if not o.need(2):
        return
    mei = d[1]
    o.fields["mei_type"] = mei
    if mei != 0x0E:
        o.fields["data"] = d[2:]
        return
    if o.role == "request":
        o.fixed(4)
        if len(d) >= 3:
            code = d[2]
            o.fields["read_device_id_code"] = code
            if not 1 <= code <= 4:
                o.bad.append(f"read device id code {code} outside 1..4")
        if len(d) >= 4:
            o.fields["object_id"] = d[3]
        return
    names = (
        "read_device_id_code",
        "conformity_level",
        "more_follows",
        "next_object_id",
        "number_of_objects",
    )
    for i, name in enumerate(names, start=2):
        if i < len(d):
            o.fields[name] = d[i]
    if not o.need(7):
        return
    if d[4] not in (0x00, 0xFF):
        o.bad.append(f"more follows 0x{d[4]:02X} is not 0x00/0xFF")
    objects: list[tuple[int, str]] = []
    i = 7
    while i < len(d):
        if i + 2 > len(d) or i + 2 + d[i + 1] > len(d):
            o.bad.append(f"object {len(objects) + 1} truncated")
            break
        objects.append((d[i], _text(d[i + 2 : i + 2 + d[i + 1]])))
        i += 2 + d[i + 1]
    if len(objects) != d[6]:
        o.bad.append(f"{len(objects)} objects but number of objects {d[6]}")
    o.fields["objects"] = tuple(objects)


#: Field decoders of the codes whose layout is their own (no ``shape`` in the table):
#: fc -> (request decoder, response decoder).
BY_CODE: Final[dict[int, tuple[Decoder, Decoder]]] = {
    0x07: (_empty_req, _exc_status_resp),
    0x08: (_diagnostics, _diagnostics),
    0x0B: (_empty_req, _event_counter_resp),
    0x0C: (_empty_req, _event_log_resp),
    0x11: (_empty_req, _server_id_resp),
    0x14: (_read_file_req, _read_file_resp),
    0x15: (_write_file, _write_file),
    0x18: FIFO,
    0x2B: (_mei, _mei),
}
