"""Modbus PDUs: decoding of every public function code, length prediction, encoders.

A PDU is the function code followed by its data, exactly as in the robot's
monitor window (no unit id, MBAP header or CRC). This module owns:

* :func:`decode_pdu` -- bytes -> :class:`mbmon.model.Pdu`; never raises for any
  input; spec violations become ``Pdu.malformed`` (``"; "``-joined reasons)
  while everything that can still be read is decoded.
* :func:`pdu_length` -- how long a PDU is from its first bytes (RTU framing);
  :func:`simple_length_rules` -- its function-free rules, for a framer that
  inlines the common case.
* name tables for the formatter, :func:`table_of` for annotators, and small
  encoders for tests, the simulator and benchmarks.

Field conventions of the decoded :class:`~mbmon.model.Pdu` (``fc`` never has
the 0x80 bit; fields a code does not have stay ``None``; ``fields`` is a
read-only mapping, nested record dicts are plain dicts):

=========  ==================================================================
fc         request / response
=========  ==================================================================
01 02      req: address, count. resp: byte_count, values = bits 0/1, LSB of
           the first byte first; trimmed to ``request.count`` when the paired
           request is given and the bytes hold that many bits, else every bit.
03 04      req: address, count. resp: byte_count, values = unsigned 16-bit.
05         address, count=1, values=(1,) for 0xFF00, (0,) for 0x0000; any other
           value: values None, ``fields["raw_value"]``, malformed.
06         address, count=1, values=(value,).
07         req: nothing. resp: ``fields["status"]`` (the 8 status bits as int).
08         ``fields["sub_function"]``, ``fields["data"]`` (bytes after the
           sub-function); values = data as 16-bit words when its length is even.
           Sub-function 0x00 echoes any number of bytes, 0x15 replies carry
           Modbus Plus statistics; every other one is 5 bytes. 0x04 (Force
           Listen Only Mode) is never answered.
0B         req: nothing. resp: fields ``status``, ``event_count``.
0C         req: nothing. resp: byte_count, fields ``status``, ``event_count``,
           ``message_count``, ``events`` (bytes, newest first).
0F 10      req: address, count, byte_count, values (bits trimmed to count /
           registers). resp: address, count.
11         req: nothing. resp: byte_count, ``fields["server_id"]`` (bytes before
           the last), ``fields["run_indicator"]`` (last byte, 0x00 OFF / 0xFF
           ON; absent when byte_count is 0).
14         byte_count; ``fields["records"]`` = tuple of dicts. Request dicts:
           reference_type, file_number, record_number, record_length. Response
           dicts: reference_type, record_length (words read), data (tuple of
           words); plus file_number and record_number copied from the paired
           request when it has as many sub-requests.
15         byte_count; ``fields["records"]`` = tuple of dicts reference_type,
           file_number, record_number, record_length, data (tuple of words).
           The response is an echo of the request.
16         address, fields ``and_mask``, ``or_mask`` (request and response).
17         req: address/count = the READ part; fields ``write_address``,
           ``write_count``, ``write_byte_count``, ``write_values``.
           resp: byte_count, values (read registers).
18         req: address = FIFO pointer address. resp: byte_count (2-byte field),
           ``fields["fifo_count"]``, values.
2B         ``fields["mei_type"]``. MEI 0x0E (Read Device Identification) req:
           fields ``read_device_id_code``, ``object_id``; resp: fields
           ``read_device_id_code``, ``conformity_level``, ``more_follows``,
           ``next_object_id``, ``number_of_objects``, ``objects`` = tuple of
           (object_id, text); text is UTF-8 when valid, else Latin-1. Other MEI
           types (0x0D CANopen, ...): ``fields["data"]`` = bytes after the MEI
           type.
=========  ==================================================================

Exception responses (``response=True`` and fc & 0x80): kind EXCEPTION,
``exception_code``; an unknown code is not malformed (the name table just lacks
it). Unknown and user-defined function codes (0x41-0x48, 0x64-0x6E, ...) keep
their bytes after the function code in ``fields["data"]`` and are not
malformed. A request with the 0x80 bit set is decoded the same way, with
``fc`` cleared and a malformed reason.

Checked and reported in ``malformed`` (short, lower-case, specific): the
spec's quantity limits, from the function-code table's ``max_count`` and
``max_write_count`` (read bits 1..2000, read registers 1..125, write coils
1..1968, write registers 1..123, 0x17 read 1..125 / write 1..121),
address + count past 65536, byte counts that disagree with the count, with the
paired request or with the bytes present (``"byte count 6 but 4 data
bytes"``), truncation (``"truncated: 0x03 request needs 5 bytes, got 3"``) and
trailing bytes.

Pure: no I/O.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable, Mapping, Sequence
from itertools import chain
from types import MappingProxyType
from typing import Any, Final

from mbmon.model import EMPTY, Kind, Pdu, fast_constructor
from mbmon.protocol.functions import (
    FUNCTIONS,
    NEED_MORE,
    SHIPPED,
    FunctionCode,
    LengthRule,
    derived,
)

__all__ = [
    "DIAGNOSTIC_NAMES",
    "EXCEPTION_NAMES",
    "FUNCTION_NAMES",
    "MEI_OBJECT_NAMES",
    "MEI_TYPE_NAMES",
    "NEED_MORE",
    "NO_REPLY_DIAGNOSTICS",
    "READ_DEVICE_ID_NAMES",
    "decode_pdu",
    "encode_exception",
    "encode_read_request",
    "encode_read_response",
    "encode_write_multiple_request",
    "encode_write_multiple_response",
    "encode_write_single",
    "pdu_length",
    "simple_length_rules",
    "table_of",
    "with_malformed",
]

#: Names of the function codes, from the one table (:mod:`mbmon.protocol.functions`;
#: kept up to date by :func:`_from_table`).
FUNCTION_NAMES: Final[dict[int, str]] = {}

EXCEPTION_NAMES: Final[dict[int, str]] = {
    0x01: "Illegal Function",
    0x02: "Illegal Data Address",
    0x03: "Illegal Data Value",
    0x04: "Server Device Failure",
    0x05: "Acknowledge",
    0x06: "Server Device Busy",
    0x08: "Memory Parity Error",
    0x0A: "Gateway Path Unavailable",
    0x0B: "Gateway Target Device Failed To Respond",
}

# Sub-functions of 0x08 defined by the spec; 0x05-0x09 and 0x13 are reserved.
DIAGNOSTIC_NAMES: Final[dict[int, str]] = {
    0x00: "Return Query Data",
    0x01: "Restart Communications Option",
    0x02: "Return Diagnostic Register",
    0x03: "Change ASCII Input Delimiter",
    0x04: "Force Listen Only Mode",
    0x0A: "Clear Counters and Diagnostic Register",
    0x0B: "Return Bus Message Count",
    0x0C: "Return Bus Communication Error Count",
    0x0D: "Return Bus Exception Error Count",
    0x0E: "Return Server Message Count",
    0x0F: "Return Server No Response Count",
    0x10: "Return Server NAK Count",
    0x11: "Return Server Busy Count",
    0x12: "Return Bus Character Overrun Count",
    0x14: "Clear Overrun Counter and Flag",
    0x15: "Get/Clear Modbus Plus Statistics",
}

#: Diagnostics sub-functions a server never answers (spec 6.8: "No response is
#: returned" to 04 Force Listen Only Mode): a request of one is not "No response".
NO_REPLY_DIAGNOSTICS: Final = frozenset({0x04})

#: Read Device ID codes of a Read Device Identification (MEI 0x0E) request.
READ_DEVICE_ID_NAMES: Final[dict[int, str]] = {
    0x01: "basic",
    0x02: "regular",
    0x03: "extended",
    0x04: "one object",
}

MEI_TYPE_NAMES: Final[dict[int, str]] = {
    0x0D: "CANopen General Reference",
    0x0E: "Read Device Identification",
}

MEI_OBJECT_NAMES: Final[dict[int, str]] = {
    0x00: "VendorName",
    0x01: "ProductCode",
    0x02: "MajorMinorRevision",
    0x03: "VendorUrl",
    0x04: "ProductName",
    0x05: "ModelName",
    0x06: "UserApplicationName",
}

_TABLES: Final[dict[int, str]] = {}  # by :func:`_from_table`


def table_of(fc: int) -> str | None:
    """The data table a function code addresses, or ``None`` when it addresses none.

    ``"coil"`` (01/05/0F), ``"discrete_input"`` (02), ``"holding_register"``
    (03/06/10/16/17) or ``"input_register"`` (04); the exception bit is ignored.
    """
    return _TABLES.get(fc & 0x7F)


# --------------------------------------------------------------------------- lengths

# Length rules by code, from the one table: int = fixed; (i, base) = base + data[i];
# a function of the first bytes for the codes whose length depends on a sub-code.
_REQ_LEN: Final[dict[int, LengthRule]] = {}  # by :func:`_from_table`
_RESP_LEN: Final[dict[int, LengthRule]] = {}
#: Function code -> the spec's quantity limit of its count (by :func:`_from_table`).
_MAX_COUNT: Final[dict[int, int]] = {}


def pdu_length(data: bytes | bytearray | memoryview, response: bool) -> int | None:
    """Full PDU length (function code + data) predicted from its first bytes.

    Returns :data:`NEED_MORE` when the bytes present cannot tell yet (e.g. the
    byte-count byte has not arrived), ``None`` when the function code has no
    predictable length and only CRC scanning can find the end: unknown and
    user-defined codes, requests with the 0x80 bit, 0x2B responses and 0x2B
    requests other than MEI 0x0E, 0x08 sub-function 0x00 (Return Query Data
    echoes any number of bytes) and 0x08 sub-function 0x15 responses (Modbus
    Plus statistics). Every other 0x08 is 5 bytes. An exception response is 2.
    """
    n = len(data)
    if n == 0:
        return NEED_MORE
    fc = data[0]
    if fc & 0x80:
        return 2 if response else None
    spec = (_RESP_LEN if response else _REQ_LEN).get(fc)
    if spec is None:
        return None
    if type(spec) is int:
        return spec
    if type(spec) is tuple:
        index, base = spec
        return NEED_MORE if n <= index else base + data[index]
    return spec(data)  # type: ignore[operator]


def simple_length_rules(response: bool) -> dict[int, int | tuple[int, int]]:
    """The rules :func:`pdu_length` applies without a function, for a framer that
    inlines the common case: function code -> fixed PDU length (int) or
    ``(i, base)`` (length ``base + data[i]``, :data:`NEED_MORE` while ``data[i]``
    is missing). Responses include the exception codes 0x81..0xFF (2 bytes).
    Codes absent here go through :func:`pdu_length` (a function rule, or no
    predictable length). Same answers as :func:`pdu_length` by construction: it
    reads the same tables (tested)."""
    rules: dict[int, int | tuple[int, int]] = {
        code: rule
        for code, rule in (_RESP_LEN if response else _REQ_LEN).items()
        if type(rule) is int or type(rule) is tuple
    }
    if response:
        rules.update(dict.fromkeys(range(0x81, 0x100), 2))
    return rules


# --------------------------------------------------------------------------- decoding

_BITS: Final[tuple[tuple[int, ...], ...]] = tuple(
    tuple((b >> i) & 1 for i in range(8)) for b in range(256)
)


def _bits(data: bytes) -> tuple[int, ...]:
    return tuple(chain.from_iterable(map(_BITS.__getitem__, data)))


def _words(data: bytes) -> tuple[int, ...]:
    n = len(data) // 2
    return struct.unpack_from(f">{n}H", data) if n else ()


def _u16(d: bytes, i: int) -> int | None:
    return (d[i] << 8) | d[i + 1] if len(d) >= i + 2 else None


class _Out:
    """What one decoder found: the common Pdu fields, extra fields and reasons."""

    __slots__ = ("address", "bad", "byte_count", "count", "d", "fc", "fields", "role", "values")

    def __init__(self, d: bytes, fc: int, role: str) -> None:
        self.d = d
        self.fc = fc
        self.role = role  # "request" / "response", for reasons
        self.address: int | None = None
        self.count: int | None = None
        self.byte_count: int | None = None
        self.values: tuple[int, ...] | None = None
        self.fields: dict[str, Any] = {}
        self.bad: list[str] = []

    def need(self, n: int) -> bool:
        """True when at least ``n`` bytes are present; else records the truncation."""
        if len(self.d) >= n:
            return True
        self.bad.append(
            f"truncated: 0x{self.fc:02X} {self.role} needs {n} bytes, got {len(self.d)}"
        )
        return False

    def fixed(self, n: int) -> None:
        """Check an exactly ``n``-byte PDU (truncation or trailing bytes)."""
        if self.need(n) and len(self.d) > n:
            self.trailing(len(self.d) - n)

    def trailing(self, extra: int) -> None:
        self.bad.append(f"{extra} trailing byte{'s' if extra != 1 else ''}")

    def limit(self, what: str, value: int | None, hi: int) -> None:
        if value is not None and not 1 <= value <= hi:
            self.bad.append(f"{what} {value} outside 1..{hi}")

    def span(self, address: int | None, count: int | None) -> None:
        if address is not None and count is not None and address + count > 0x10000:
            self.bad.append(f"address {address} + count {count} exceeds 65536")

    def counted(self, at: int, width: int = 1) -> bytes:
        """Bytes after a byte-count field at ``d[at]``; checks it against the bytes present."""
        d = self.d
        bc = d[at] if width == 1 else (d[at] << 8) | d[at + 1]
        self.byte_count = bc
        start = at + width
        have = len(d) - start
        if have != bc:
            self.bad.append(f"byte count {bc} but {have} data bytes")
        return d[start : start + bc]


def _paired(request: Pdu | None, fc: int) -> Pdu | None:
    if request is not None and request.fc == fc and request.kind is Kind.REQUEST:
        return request
    return None


def _read_req(o: _Out, request: Pdu | None) -> None:
    d = o.d
    if len(d) == 5:  # the usual case, decided without the helpers (same result)
        address = (d[1] << 8) | d[2]
        count = (d[3] << 8) | d[4]
        o.address = address
        o.count = count
        if not 1 <= count <= _MAX_COUNT[o.fc]:
            o.limit("count", count, _MAX_COUNT[o.fc])
        if address + count > 0x10000:
            o.span(address, count)
        return
    o.fixed(5)
    o.address, o.count = _u16(d, 1), _u16(d, 3)
    o.limit("count", o.count, _MAX_COUNT[o.fc])
    o.span(o.address, o.count)


def _bits_resp(o: _Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    bits = _bits(data)
    req = _paired(request, o.fc)
    n = req.count if req is not None else None
    if n is not None:
        want = (n + 7) // 8
        if o.byte_count != want:
            o.bad.append(f"byte count {o.byte_count} but {n} bits need {want}")
        if len(bits) >= n:
            bits = bits[:n]
    elif o.byte_count == 0:
        o.bad.append("byte count 0")
    o.values = bits


def _regs_resp(o: _Out, request: Pdu | None) -> None:
    d = o.d
    if len(d) < 2:
        o.need(2)
        return
    bc = d[1]
    if request is None and bc and not bc & 1 and len(d) == bc + 2:
        # the usual unpaired answer, decided without the helpers (same result)
        o.byte_count = bc
        o.values = struct.unpack_from(f">{bc >> 1}H", d, 2)
        return
    data = o.counted(1)
    bc = o.byte_count or 0
    if bc % 2:
        o.bad.append(f"odd byte count {bc}")
    req = _paired(request, o.fc)
    n = req.count if req is not None else None
    if n is not None:
        if bc != 2 * n:
            o.bad.append(f"byte count {bc} but {n} registers need {2 * n}")
    elif bc == 0:
        o.bad.append("byte count 0")
    o.values = _words(data)


def _write_coil(o: _Out, request: Pdu | None) -> None:
    o.fixed(5)
    o.address = _u16(o.d, 1)
    raw = _u16(o.d, 3)
    o.count = 1
    if raw == 0xFF00:
        o.values = (1,)
    elif raw == 0x0000:
        o.values = (0,)
    elif raw is not None:
        o.fields["raw_value"] = raw
        o.bad.append(f"coil value 0x{raw:04X} is not 0xFF00/0x0000")


def _write_reg(o: _Out, request: Pdu | None) -> None:
    o.fixed(5)
    o.address = _u16(o.d, 1)
    v = _u16(o.d, 3)
    o.count = 1
    if v is not None:
        o.values = (v,)


def _empty_req(o: _Out, request: Pdu | None) -> None:
    o.fixed(1)


def _exc_status_resp(o: _Out, request: Pdu | None) -> None:
    o.fixed(2)
    if len(o.d) >= 2:
        o.fields["status"] = o.d[1]


def _diagnostics(o: _Out, request: Pdu | None) -> None:
    d = o.d
    if not o.need(3):
        return
    sub = (d[1] << 8) | d[2]
    data = d[3:]
    o.fields["sub_function"] = sub
    o.fields["data"] = data
    if len(data) % 2 == 0:
        o.values = _words(data)
    if sub == 0x00:
        req = _paired(request, 0x08)
        if req is not None and req.fields.get("sub_function") == 0 and req.raw != d:
            o.bad.append("echo differs from request")
    elif not (sub == 0x15 and o.role == "response"):
        o.fixed(5)


def _event_counter_resp(o: _Out, request: Pdu | None) -> None:
    o.fixed(5)
    status, events = _u16(o.d, 1), _u16(o.d, 3)
    if status is not None:
        o.fields["status"] = status
    if events is not None:
        o.fields["event_count"] = events


def _event_log_resp(o: _Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    if (o.byte_count or 0) < 6:
        o.bad.append(f"byte count {o.byte_count} below 6")
    for name, i in (("status", 0), ("event_count", 2), ("message_count", 4)):
        v = _u16(data, i)
        if v is not None:
            o.fields[name] = v
    o.fields["events"] = data[6:]


def _write_multi_req(o: _Out, request: Pdu | None) -> None:
    d = o.d
    coils = FUNCTIONS[o.fc].bits
    o.address, o.count = _u16(d, 1), _u16(d, 3)
    if not o.need(6):
        return
    data = o.counted(5)
    bc = o.byte_count or 0
    n = o.count or 0
    o.limit("count", o.count, _MAX_COUNT[o.fc])
    o.span(o.address, o.count)
    if coils:
        want = (n + 7) // 8
        bits = _bits(data)
        if bc != want:
            o.bad.append(f"byte count {bc} but {n} bits need {want}")
        o.values = bits[:n] if len(bits) >= n else bits
    else:
        if bc != 2 * n:
            o.bad.append(f"byte count {bc} but {n} registers need {2 * n}")
        o.values = _words(data)


def _write_multi_resp(o: _Out, request: Pdu | None) -> None:
    o.fixed(5)
    o.address, o.count = _u16(o.d, 1), _u16(o.d, 3)
    o.limit("count", o.count, _MAX_COUNT[o.fc])
    o.span(o.address, o.count)


def _server_id_resp(o: _Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    o.fields["server_id"] = data[:-1]
    if data:
        o.fields["run_indicator"] = data[-1]


def _file_check(o: _Out, rec: dict[str, Any]) -> None:
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


def _read_file_req(o: _Out, request: Pdu | None) -> None:
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


def _read_file_resp(o: _Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    if o.byte_count == 0:  # as the request (7..245) and both 0x15 frames (9..251)
        o.bad.append("byte count 0")
    records = []
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
        rec["data"] = _words(words)
        _file_check(o, rec)
        records.append(rec)
        i += 1 + length
    req = _paired(request, 0x14)
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


def _write_file(o: _Out, request: Pdu | None) -> None:
    if not o.need(2):
        return
    data = o.counted(1)
    bc = o.byte_count or 0
    if not 0x09 <= bc <= 0xFB:
        o.bad.append(f"byte count {bc} outside 9..251")
    records = []
    i = 0
    while i < len(data):
        if i + 7 > len(data):
            o.bad.append(f"sub-request {len(records) + 1} truncated")
            break
        rec = _file_header(data, i)
        end = i + 7 + 2 * rec["record_length"]
        if end > len(data):
            o.bad.append(f"sub-request {len(records) + 1} truncated")
        rec["data"] = _words(data[i + 7 : end])
        _file_check(o, rec)
        records.append(rec)
        i = end
    o.fields["records"] = tuple(records)
    req = _paired(request, 0x15)
    if o.role == "response" and req is not None and req.raw != o.d:
        o.bad.append("echo differs from request")


def _mask_write(o: _Out, request: Pdu | None) -> None:
    o.fixed(7)
    o.address = _u16(o.d, 1)
    for name, i in (("and_mask", 3), ("or_mask", 5)):
        v = _u16(o.d, i)
        if v is not None:
            o.fields[name] = v


def _rw_multi_req(o: _Out, request: Pdu | None) -> None:
    d = o.d
    o.address, o.count = _u16(d, 1), _u16(d, 3)
    waddr, wcount = _u16(d, 5), _u16(d, 7)
    if waddr is not None:
        o.fields["write_address"] = waddr
    if wcount is not None:
        o.fields["write_count"] = wcount
    spec = FUNCTIONS[o.fc]
    o.limit("read count", o.count, spec.max_count or 0)
    o.limit("write count", wcount, spec.max_write_count or 0)
    o.span(o.address, o.count)
    o.span(waddr, wcount)
    if not o.need(10):
        return
    data = o.counted(9)
    o.byte_count = None  # the only byte count of a 0x17 request is the write part's
    wbc = d[9]
    o.fields["write_byte_count"] = wbc
    n = wcount or 0
    if wbc != 2 * n:
        o.bad.append(f"write byte count {wbc} but {n} registers need {2 * n}")
    o.fields["write_values"] = _words(data)


def _fifo_req(o: _Out, request: Pdu | None) -> None:
    o.fixed(3)
    o.address = _u16(o.d, 1)


def _fifo_resp(o: _Out, request: Pdu | None) -> None:
    if not o.need(3):
        return
    data = o.counted(1, width=2)
    bc = o.byte_count or 0
    fifo = _u16(data, 0)
    if fifo is None:
        o.bad.append("no fifo count")
        return
    o.fields["fifo_count"] = fifo
    if fifo > 31:
        o.bad.append(f"fifo count {fifo} exceeds 31")
    if bc != 2 + 2 * fifo:
        o.bad.append(f"byte count {bc} but fifo count {fifo} needs {2 + 2 * fifo}")
    o.values = _words(data[2:])


def _text(b: bytes) -> str:
    try:
        return b.decode("utf-8")
    except UnicodeDecodeError:
        return b.decode("latin-1")


def _mei(o: _Out, request: Pdu | None) -> None:
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
    objects = []
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


_Decoder = Callable[[_Out, Pdu | None], None]

#: Field decoders of the codes whose layout is their own (no ``shape`` in the table):
#: fc -> (request decoder, response decoder).
_BY_CODE: Final[dict[int, tuple[_Decoder, _Decoder]]] = {
    0x07: (_empty_req, _exc_status_resp),
    0x08: (_diagnostics, _diagnostics),
    0x0B: (_empty_req, _event_counter_resp),
    0x0C: (_empty_req, _event_log_resp),
    0x11: (_empty_req, _server_id_resp),
    0x14: (_read_file_req, _read_file_resp),
    0x15: (_write_file, _write_file),
    0x18: (_fifo_req, _fifo_resp),
    0x2B: (_mei, _mei),
}
#: Field decoders of a table ``shape``: (shape, bits) -> (request, response decoder).
_BY_SHAPE: Final[dict[tuple[str, bool], tuple[_Decoder, _Decoder]]] = {
    ("read", True): (_read_req, _bits_resp),
    ("read", False): (_read_req, _regs_resp),
    ("write_single", True): (_write_coil, _write_coil),
    ("write_single", False): (_write_reg, _write_reg),
    ("write_multiple", True): (_write_multi_req, _write_multi_resp),
    ("write_multiple", False): (_write_multi_req, _write_multi_resp),
    ("mask_write", False): (_mask_write, _mask_write),
    ("read_write", False): (_rw_multi_req, _regs_resp),
}
#: The codes :func:`_well_formed` decides: 0x01..0x10 with a shape it knows, while
#: their row is the shipped one (by :func:`_from_table`).
_FAST: Final[set[int]] = set()
_FAST_SHAPES: Final = ("read", "write_single", "write_multiple")
#: fc -> (request decoder, response decoder), from the table (by :func:`_from_table`).
_DECODERS: Final[dict[int, tuple[_Decoder, _Decoder]]] = {}


def _fields(f: dict[str, Any]) -> Mapping[str, Any]:
    return MappingProxyType(f) if f else EMPTY


def decode_pdu(
    data: bytes | bytearray | memoryview, response: bool, request: Pdu | None = None
) -> Pdu:
    """Decode one PDU (``data`` starts at the function code) into a :class:`Pdu`.

    ``response`` says which way it travels (server reply when True).
    ``request`` is the paired request, used only for context: the bit count of
    an 01/02 reply, the read count of 0x17, file sub-requests of 0x14, echo
    checks. Never raises: spec violations become ``malformed``.
    """
    d = data if type(data) is bytes else bytes(data)
    if request is None:
        if response:
            cache = _RESPONSES
            which = 1
        else:
            cache = _REQUESTS
            which = 0
        hit = cache.get(d)
        if hit is not None:
            return hit
        pdu = _decode(d, response, None)
        held = _held[which]
        if held > _CACHE_BYTES or len(cache) >= _CACHE_SIZE:
            cache.clear()
            held = 0
        cache[d] = pdu
        _held[which] = held + len(d)
        return pdu
    paired_key = (d, response, id(request))
    paired = _PAIRED_CACHE.get(paired_key)
    if paired is not None and paired[0] is request:
        return paired[1]
    pdu = _decode(d, response, request)
    if len(_PAIRED_CACHE) >= _CACHE_SIZE or _held[2] > _CACHE_BYTES:
        _PAIRED_CACHE.clear()
        _held[2] = 0
    _PAIRED_CACHE[paired_key] = (request, pdu)
    _held[2] += len(d)
    return pdu


#: Decoded PDUs by bytes, requests and responses apart (keyed by the bytes alone: no
#: key tuple to build and hash per PDU). Polling repeats the same PDUs over and over
#: and a Pdu is immutable, so a repeat is a dict hit; a cache is emptied when full.
_REQUESTS: dict[bytes, Pdu] = {}
_RESPONSES: dict[bytes, Pdu] = {}
_CACHE_SIZE: Final = 8192
#: PDU bytes each cache may hold before it is emptied: caches are bounded in bytes,
#: not only in entries (a decoded Pdu, values included, takes about 20x its bytes,
#: so each cache stays within a few MB whatever the PDUs' sizes).
_CACHE_BYTES: Final = 1 << 18
_held = [0, 0, 0]  # PDU bytes in _REQUESTS, _RESPONSES (index: response), _PAIRED_CACHE
#: The same for PDUs decoded with their request, by (bytes, response, id(request)):
#: requests come from ``_REQUESTS`` too, so a polled read's answer is decoded once
#: (and is the same object each time, which lets ``mbmon.format`` cache by it).
#: The request is kept with the PDU so that an id is never taken for a later object's.
_PAIRED_CACHE: dict[tuple[bytes, bool, int], tuple[Pdu, Pdu]] = {}


def _decode(d: bytes, response: bool, request: Pdu | None) -> Pdu:
    """:func:`decode_pdu` without the cache."""
    if not d:
        return Pdu(
            raw=d,
            fc=0,
            kind=Kind.RESPONSE if response else Kind.REQUEST,
            malformed="empty PDU",
        )
    code = d[0]
    fc = code & 0x7F
    if code & 0x80:
        if response:
            bad = []
            exc = d[1] if len(d) >= 2 else None
            if exc is None:
                bad.append("truncated: exception response needs 2 bytes, got 1")
            elif len(d) > 2:
                n = len(d) - 2
                bad.append(f"{n} trailing byte{'s' if n != 1 else ''}")
            return Pdu(
                raw=d,
                fc=fc,
                kind=Kind.EXCEPTION,
                exception_code=exc,
                malformed="; ".join(bad) or None,
            )
        return Pdu(
            raw=d,
            fc=fc,
            kind=Kind.REQUEST,
            fields=_fields({"data": d[1:]}),
            malformed=f"exception bit set in request function code 0x{code:02X}",
        )
    if request is None and fc in _FAST:
        pdu = _well_formed(d, fc, response)
        if pdu is not None:
            return pdu
    return _decode_general(d, fc, response, request)


def _well_formed(d: bytes, fc: int, response: bool) -> Pdu | None:
    """The frequent PDUs (01-06, 0F, 10) when they break no rule, decided without
    the collector and the helper calls; ``None`` for anything else (other codes,
    any reason to report), which :func:`_decode_general` decides. Where it answers
    it gives the very same Pdu as the field decoders (``tests/protocol/
    test_pdu_props.py`` compares the two on any bytes): they own the rules, this
    only skips the bookkeeping for PDUs with nothing to report.
    """
    n = len(d)
    if response:
        if fc <= 0x04:
            if n < 3:
                return None
            bc = d[1]
            if n != bc + 2:
                return None
            if fc >= 0x03:
                if bc & 1:
                    return None
                values = struct.unpack_from(f">{bc >> 1}H", d, 2)
            else:
                values = _bits(d[2:])
            return _new_pdu(d, fc, _RESPONSE, None, None, None, bc, values, EMPTY, None)
        kind = _RESPONSE
    else:
        kind = _REQUEST
        if fc <= 0x04:
            if n != 5:
                return None
            address = (d[1] << 8) | d[2]
            count = (d[3] << 8) | d[4]
            if not 1 <= count <= _MAX_COUNT[fc] or address + count > 0x10000:
                return None
            return _new_pdu(d, fc, _REQUEST, None, address, count, None, None, EMPTY, None)
        if fc >= 0x0F and n != 5:  # 0F / 10 request with its data
            if n < 6:
                return None
            bc = d[5]
            count = (d[3] << 8) | d[4]
            address = (d[1] << 8) | d[2]
            if n - 6 != bc or count < 1 or address + count > 0x10000:
                return None
            if fc == 0x0F:
                if count > _MAX_COUNT[fc] or bc != (count + 7) >> 3:
                    return None
                values = _bits(d[6:])[:count]
            else:
                if count > _MAX_COUNT[fc] or bc != 2 * count:
                    return None
                values = struct.unpack_from(f">{count}H", d, 6)
            return _new_pdu(d, fc, _REQUEST, None, address, count, bc, values, EMPTY, None)
    if n != 5:
        return None
    address = (d[1] << 8) | d[2]
    value = (d[3] << 8) | d[4]
    if fc == 0x05:
        if value == 0xFF00:
            return _new_pdu(d, 5, kind, None, address, 1, None, _ON, EMPTY, None)
        if value == 0:
            return _new_pdu(d, 5, kind, None, address, 1, None, _OFF, EMPTY, None)
        return None
    if fc == 0x06:
        return _new_pdu(d, 6, kind, None, address, 1, None, (value,), EMPTY, None)
    if fc >= 0x0F and response:  # 0F / 10 response: address, count
        if not 1 <= value <= _MAX_COUNT[fc] or address + value > 0x10000:
            return None
        return _new_pdu(d, fc, kind, None, address, value, None, None, EMPTY, None)
    return None


_ON: Final = (1,)
_OFF: Final = (0,)


def _decode_general(d: bytes, fc: int, response: bool, request: Pdu | None) -> Pdu:
    """:func:`_decode` of a PDU with a function code, by the field decoders."""
    kind = _RESPONSE if response else _REQUEST
    decoders = _DECODERS.get(fc)
    if decoders is None:
        return Pdu(
            raw=d,
            fc=fc,
            kind=kind,
            fields=_fields({"data": d[1:]}),
            malformed="function code 0 is invalid" if fc == 0 else None,
        )
    o = _Out(d, fc, "response" if response else "request")
    try:
        decoders[1 if response else 0](o, request)
    except Exception as err:  # a decoder bug must not stop the pipeline
        o.bad.append(f"internal decoder error: {type(err).__name__}")
    f = o.fields
    bad = o.bad
    return _new_pdu(
        d,
        fc,
        kind,
        None,
        o.address,
        o.count,
        o.byte_count,
        o.values,
        MappingProxyType(f) if f else EMPTY,
        "; ".join(bad) if bad else None,
    )


_RESPONSE: Final = Kind.RESPONSE  # module constants: an enum class attribute costs more
_REQUEST: Final = Kind.REQUEST
_new_pdu = fast_constructor(Pdu)  # per decoded PDU (cache misses): Pdu(...) by its slots


@derived
def _from_table() -> None:
    """Copy names, tables, length rules, quantity limits and field decoders out of
    the one table, and forget decoded PDUs: run again when a code is registered."""
    for copy in (FUNCTION_NAMES, _TABLES, _REQ_LEN, _RESP_LEN, _MAX_COUNT, _DECODERS):
        copy.clear()
    for code, f in FUNCTIONS.items():
        FUNCTION_NAMES[code] = f.name
        if f.table is not None:
            _TABLES[code] = f.table
        if f.request_length is not None:
            _REQ_LEN[code] = f.request_length
        if f.response_length is not None:
            _RESP_LEN[code] = f.response_length
        if f.max_count is not None:
            _MAX_COUNT[code] = f.max_count
        decoders = _BY_CODE.get(code) if f.shape is None else _BY_SHAPE[(f.shape, f.bits)]
        if decoders is not None:
            _DECODERS[code] = decoders
    _FAST.clear()
    _FAST.update(
        code
        for code, f in FUNCTIONS.items()
        if code <= 0x10 and f.shape in _FAST_SHAPES and f is SHIPPED.get(code)
    )
    for cache in (_REQUESTS, _RESPONSES, _PAIRED_CACHE):
        cache.clear()
    _held[:] = [0, 0, 0]


def with_malformed(pdu: Pdu, reason: str) -> Pdu:
    """``pdu`` with ``reason`` put first in its ``malformed`` (a breach found outside
    the PDU, e.g. by the framing), the PDU's own reasons after it."""
    text = reason if pdu.malformed is None else f"{reason}; {pdu.malformed}"
    return dataclasses.replace(pdu, malformed=text)


# --------------------------------------------------------------------------- encoders


def _u8(name: str, v: int) -> int:
    if not 0 <= v <= 0xFF:
        raise ValueError(f"{name} {v} does not fit in a byte")
    return v


def _w(name: str, v: int) -> bytes:
    if not 0 <= v <= 0xFFFF:
        raise ValueError(f"{name} {v} does not fit in 16 bits")
    return v.to_bytes(2, "big")


def _pack_bits(values: Sequence[int]) -> bytes:
    out = bytearray((len(values) + 7) // 8)
    for i, v in enumerate(values):
        if v:
            out[i >> 3] |= 1 << (i & 7)
    return bytes(out)


def _pack_words(values: Sequence[int]) -> bytes:
    return b"".join(_w("value", v) for v in values)


def encode_read_request(fc: int, address: int, count: int) -> bytes:
    """Read request PDU (01/02/03/04): fc, address, count. No limit checks."""
    return bytes((_u8("fc", fc),)) + _w("address", address) + _w("count", count)


def encode_read_response(fc: int, values: Sequence[int], count: int | None = None) -> bytes:
    """Read response PDU: bits (01/02, LSB first) or registers (03/04/17).

    For bits, ``count`` is how many of ``values`` to pack (default all); the
    last byte is zero-padded. ``count`` is ignored for registers.
    """
    spec = _shaped(fc, "read", "read_write")
    if spec is not None and spec.bits:
        n = len(values) if count is None else count
        if not 0 <= n <= len(values):
            raise ValueError(f"count {n} but {len(values)} values")
        data = _pack_bits(values[:n])
    elif spec is not None:
        data = _pack_words(values)
    else:
        raise ValueError(f"0x{fc:02X} is not a read function code")
    return bytes((fc, _u8("byte count", len(data)))) + data


def encode_write_single(fc: int, address: int, value: int | bool) -> bytes:
    """Write single PDU (05/06; the response is identical).

    For 05 a ``bool`` becomes 0xFF00/0x0000 and an ``int`` is sent as is (so
    tests can build illegal coil values); for 06 ``value`` is the register.
    """
    spec = _shaped(fc, "write_single")
    if spec is None:
        raise ValueError(f"0x{fc:02X} is not a write single function code")
    if spec.bits and isinstance(value, bool):
        value = 0xFF00 if value else 0x0000
    return bytes((fc,)) + _w("address", address) + _w("value", int(value))


def encode_write_multiple_request(fc: int, address: int, values: Sequence[int]) -> bytes:
    """Write multiple request PDU: coils (0F, truthy = 1) or registers (10)."""
    spec = _shaped(fc, "write_multiple")
    if spec is None:
        raise ValueError(f"0x{fc:02X} is not a write multiple function code")
    data = _pack_bits(values) if spec.bits else _pack_words(values)
    head = bytes((fc,)) + _w("address", address) + _w("count", len(values))
    return head + bytes((_u8("byte count", len(data)),)) + data


def encode_write_multiple_response(fc: int, address: int, count: int) -> bytes:
    """Write multiple response PDU (0F/10): fc, address, count."""
    if _shaped(fc, "write_multiple") is None:
        raise ValueError(f"0x{fc:02X} is not a write multiple function code")
    return bytes((fc,)) + _w("address", address) + _w("count", count)


def _shaped(fc: int, *shapes: str) -> FunctionCode | None:
    """The table's entry for ``fc`` when its shape is one of ``shapes``."""
    spec = FUNCTIONS.get(fc)
    return spec if spec is not None and spec.shape in shapes else None


def encode_exception(fc: int, code: int) -> bytes:
    """Exception response PDU: fc | 0x80, exception code."""
    return bytes((_u8("fc", fc) | 0x80, _u8("exception code", code)))
