"""Small PDU encoders for tests, the simulator and benchmarks.

Each builds the bytes of one PDU (function code first, no unit id, header or
CRC) and raises ``ValueError`` when a field does not fit; quantity limits are
not checked, so tests can build PDUs that break them. The shapes come from the
one function-code table. Importable from :mod:`mbmon.protocol.pdu` too. Pure.
"""

from __future__ import annotations

from collections.abc import Sequence

from mbmon.protocol.functions import FUNCTIONS, FunctionCode

__all__ = [
    "encode_exception",
    "encode_read_request",
    "encode_read_response",
    "encode_write_multiple_request",
    "encode_write_multiple_response",
    "encode_write_single",
]


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
