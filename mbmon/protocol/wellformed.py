"""The fast path of PDU decoding: the frequent PDUs that break no rule.

:func:`well_formed` decides reads (01-04), single writes (05, 06) and multiple
writes (0F, 10) without the field decoders' collector and helper calls, and
gives ``None`` for anything else (other codes, any reason to report), which the
field decoders (:mod:`mbmon.protocol.fields_access`) decide. Where it answers it
gives the very same Pdu as they do (``tests/protocol/test_pdu_fast.py`` compares
the two on any bytes): they own the rules, this only skips the bookkeeping for
PDUs with nothing to report.

Which check applies to a code is table-driven: its ``shape`` and ``bits`` in the
one function-code table pick one small function per direction (``_BY_SHAPE``),
for the codes whose row is the shipped one (a re-registered code goes the
general way). The compiled core (``mbmon/core/_reader.pyx``) mirrors these
cases. Pure.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Final

from mbmon.model import EMPTY, Kind, Pdu, fast_constructor
from mbmon.protocol.fields import unpack_bits
from mbmon.protocol.functions import FUNCTIONS, SHIPPED, derived
from mbmon.protocol.lengths import MAX_COUNT

__all__ = ["well_formed"]

_RESPONSE: Final = Kind.RESPONSE  # module constants: an enum class attribute costs more
_REQUEST: Final = Kind.REQUEST
_new_pdu = fast_constructor(Pdu)  # per decoded PDU (cache misses): Pdu(...) by its slots
_ON: Final = (1,)
_OFF: Final = (0,)

_Fast = Callable[[bytes, int, Kind], "Pdu | None"]
"""One fast check: (PDU bytes, function code, kind) -> the Pdu, or ``None``."""


def _read_request(d: bytes, fc: int, kind: Kind) -> Pdu | None:
    """01-04 request: address, count within the code's limit and the address space."""
    if len(d) != 5:
        return None
    address = (d[1] << 8) | d[2]
    count = (d[3] << 8) | d[4]
    if not 1 <= count <= MAX_COUNT[fc] or address + count > 0x10000:
        return None
    return _new_pdu(d, fc, kind, None, address, count, None, None, EMPTY, None)


def _bits_response(d: bytes, fc: int, kind: Kind) -> Pdu | None:
    """01/02 response: a byte count that matches the bytes present."""
    n = len(d)
    if n < 3 or n != d[1] + 2:
        return None
    return _new_pdu(d, fc, kind, None, None, None, d[1], unpack_bits(d[2:]), EMPTY, None)


def _registers_response(d: bytes, fc: int, kind: Kind) -> Pdu | None:
    """03/04 response: an even byte count that matches the bytes present."""
    n = len(d)
    if n < 3:
        return None
    bc = d[1]
    if n != bc + 2 or bc & 1:
        return None
    values = struct.unpack_from(f">{bc >> 1}H", d, 2)
    return _new_pdu(d, fc, kind, None, None, None, bc, values, EMPTY, None)


def _write_coil(d: bytes, fc: int, kind: Kind) -> Pdu | None:
    """05 request or echo: value 0xFF00 (on) or 0x0000 (off)."""
    if len(d) != 5:
        return None
    value = (d[3] << 8) | d[4]
    if value == 0xFF00:
        values = _ON
    elif value == 0:
        values = _OFF
    else:
        return None
    return _new_pdu(d, fc, kind, None, (d[1] << 8) | d[2], 1, None, values, EMPTY, None)


def _write_register(d: bytes, fc: int, kind: Kind) -> Pdu | None:
    """06 request or echo: any value."""
    if len(d) != 5:
        return None
    value = (d[3] << 8) | d[4]
    return _new_pdu(d, fc, kind, None, (d[1] << 8) | d[2], 1, None, (value,), EMPTY, None)


def _write_multiple_head(d: bytes, fc: int) -> tuple[int, int, int] | None:
    """0F/10 request: (address, count, byte count) when the count is within the
    code's limit and the address space and the byte count matches the bytes."""
    n = len(d)
    if n < 6:
        return None
    bc = d[5]
    count = (d[3] << 8) | d[4]
    address = (d[1] << 8) | d[2]
    if n - 6 != bc or not 1 <= count <= MAX_COUNT[fc] or address + count > 0x10000:
        return None
    return address, count, bc


def _write_coils_request(d: bytes, fc: int, kind: Kind) -> Pdu | None:
    """0F request: the byte count the count of bits needs."""
    head = _write_multiple_head(d, fc)
    if head is None:
        return None
    address, count, bc = head
    if bc != (count + 7) >> 3:
        return None
    values = unpack_bits(d[6:])[:count]
    return _new_pdu(d, fc, kind, None, address, count, bc, values, EMPTY, None)


def _write_registers_request(d: bytes, fc: int, kind: Kind) -> Pdu | None:
    """10 request: the byte count the count of registers needs."""
    head = _write_multiple_head(d, fc)
    if head is None:
        return None
    address, count, bc = head
    if bc != 2 * count:
        return None
    values = struct.unpack_from(f">{count}H", d, 6)
    return _new_pdu(d, fc, kind, None, address, count, bc, values, EMPTY, None)


def _write_multiple_response(d: bytes, fc: int, kind: Kind) -> Pdu | None:
    """0F/10 response: address, count within the code's limit and the address space."""
    if len(d) != 5:
        return None
    address = (d[1] << 8) | d[2]
    count = (d[3] << 8) | d[4]
    if not 1 <= count <= MAX_COUNT[fc] or address + count > 0x10000:
        return None
    return _new_pdu(d, fc, kind, None, address, count, None, None, EMPTY, None)


#: (table shape, bits) -> (request check, response check).
_BY_SHAPE: Final[dict[tuple[str, bool], tuple[_Fast, _Fast]]] = {
    ("read", True): (_read_request, _bits_response),
    ("read", False): (_read_request, _registers_response),
    ("write_single", True): (_write_coil, _write_coil),
    ("write_single", False): (_write_register, _write_register),
    ("write_multiple", True): (_write_coils_request, _write_multiple_response),
    ("write_multiple", False): (_write_registers_request, _write_multiple_response),
}
#: The codes the fast path decides (0x01..0x10 of a shape above, while their row is
#: the shipped one): fc -> (request check, response check), by :func:`_from_table`.
FAST: Final[dict[int, tuple[_Fast, _Fast]]] = {}


@derived
def _from_table() -> None:
    """Pick each fast code's checks by its table row (again when a code is registered)."""
    FAST.clear()
    for code, f in FUNCTIONS.items():
        if code <= 0x10 and f.shape is not None and f is SHIPPED.get(code):
            checks = _BY_SHAPE.get((f.shape, f.bits))
            if checks is not None:
                FAST[code] = checks


def well_formed(d: bytes, fc: int, response: bool) -> Pdu | None:
    """The Pdu of ``d`` (function code ``fc``, no exception bit) when it is one of
    the frequent PDUs and breaks no rule; ``None`` for anything else."""
    checks = FAST.get(fc)
    if checks is None:
        return None
    if response:
        return checks[1](d, fc, _RESPONSE)
    return checks[0](d, fc, _REQUEST)
