"""Modbus PDUs: decoding of every public function code, length prediction, encoders.

A PDU is the function code followed by its data, exactly as in the robot's
monitor window (no unit id, MBAP header or CRC). This module owns
:func:`decode_pdu` -- bytes -> :class:`mbmon.model.Pdu`; never raises for any
input; spec violations become ``Pdu.malformed`` (``"; "``-joined reasons)
while everything that can still be read is decoded -- with its caches, and
:func:`with_malformed`. Every public name of the PDU layer is importable from
here; each lives in one module:

* :mod:`mbmon.protocol.lengths` -- :func:`pdu_length` (how long a PDU is from
  its first bytes: RTU framing) and :func:`simple_length_rules` (its
  function-free rules, for a framer that inlines the common case);
* :mod:`mbmon.protocol.names` -- name tables for the formatter and
  :func:`table_of` for annotators;
* :mod:`mbmon.protocol.fields`, :mod:`~mbmon.protocol.fields_access` and
  :mod:`~mbmon.protocol.fields_device` -- the field decoders, per family;
* :mod:`mbmon.protocol.wellformed` -- the fast path of the frequent PDUs;
* :mod:`mbmon.protocol.encode` -- small encoders for tests, the simulator and
  benchmarks.

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
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, Final

from mbmon.model import EMPTY, Kind, Pdu, fast_constructor
from mbmon.protocol.encode import (
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
)
from mbmon.protocol.fields import Decoder, Out
from mbmon.protocol.fields_access import BY_SHAPE
from mbmon.protocol.fields_device import BY_CODE
from mbmon.protocol.functions import FUNCTIONS, derived
from mbmon.protocol.lengths import NEED_MORE, pdu_length, simple_length_rules
from mbmon.protocol.names import (
    DIAGNOSTIC_NAMES,
    EXCEPTION_NAMES,
    FUNCTION_NAMES,
    MEI_OBJECT_NAMES,
    MEI_TYPE_NAMES,
    NO_REPLY_DIAGNOSTICS,
    READ_DEVICE_ID_NAMES,
    table_of,
)
from mbmon.protocol.wellformed import FAST as _FAST
from mbmon.protocol.wellformed import well_formed as _well_formed

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

_RESPONSE: Final = Kind.RESPONSE  # module constants: an enum class attribute costs more
_REQUEST: Final = Kind.REQUEST
_new_pdu = fast_constructor(Pdu)  # per decoded PDU (cache misses): Pdu(...) by its slots

#: fc -> (request decoder, response decoder), from the table (by :func:`_from_table`):
#: a code with a ``shape`` gets its shape's decoders, one without its own (or none).
_DECODERS: Final[dict[int, tuple[Decoder, Decoder]]] = {}


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
    o = Out(d, fc, "response" if response else "request")
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


def with_malformed(pdu: Pdu, reason: str) -> Pdu:
    """``pdu`` with ``reason`` put first in its ``malformed`` (a breach found outside
    the PDU, e.g. by the framing), the PDU's own reasons after it."""
    text = reason if pdu.malformed is None else f"{reason}; {pdu.malformed}"
    return dataclasses.replace(pdu, malformed=text)


# --------------------------------------------------------------------------- encoders


@derived
def _from_table() -> None:
    """Pick each code's field decoders by its table row and forget decoded PDUs:
    run again when a code is registered (after the tables it reads are rebuilt)."""
    _DECODERS.clear()
    for code, f in FUNCTIONS.items():
        decoders = BY_CODE.get(code) if f.shape is None else BY_SHAPE[(f.shape, f.bits)]
        if decoders is not None:
            _DECODERS[code] = decoders
    for cache in (_REQUESTS, _RESPONSES, _PAIRED_CACHE):
        cache.clear()
    _held[:] = [0, 0, 0]
