"""What the PDU field decoders share: the collector they fill and small readers.

A field decoder (one per request or response layout, in
:mod:`mbmon.protocol.fields_access` and :mod:`mbmon.protocol.fields_device`) is a
:data:`Decoder`: it reads ``Out.d`` and sets the common :class:`~mbmon.model.Pdu`
fields, extra ``fields`` and the reasons the PDU is malformed on the
:class:`Out` it is given; :func:`mbmon.protocol.pdu.decode_pdu` builds the Pdu.
Pure.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from itertools import chain
from typing import Any, Final

from mbmon.model import Kind, Pdu

__all__ = ["Decoder", "Out", "paired_request", "u16", "unpack_bits", "unpack_words"]

_BITS: Final[tuple[tuple[int, ...], ...]] = tuple(
    tuple((b >> i) & 1 for i in range(8)) for b in range(256)
)


def unpack_bits(data: bytes) -> tuple[int, ...]:
    """Bits 0/1 of ``data``, the LSB of the first byte first."""
    return tuple(chain.from_iterable(map(_BITS.__getitem__, data)))


def unpack_words(data: bytes) -> tuple[int, ...]:
    """Big-endian unsigned 16-bit words of ``data`` (an odd last byte is left out)."""
    n = len(data) // 2
    return struct.unpack_from(f">{n}H", data) if n else ()


def u16(d: bytes, i: int) -> int | None:
    """The big-endian word at ``d[i]``, ``None`` when the bytes end before it."""
    return (d[i] << 8) | d[i + 1] if len(d) >= i + 2 else None


class Out:
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
        """Record ``extra`` bytes past the end of the PDU."""
        self.bad.append(f"{extra} trailing byte{'s' if extra != 1 else ''}")

    def limit(self, what: str, value: int | None, hi: int) -> None:
        """Record a quantity outside the spec's ``1..hi``."""
        if value is not None and not 1 <= value <= hi:
            self.bad.append(f"{what} {value} outside 1..{hi}")

    def span(self, address: int | None, count: int | None) -> None:
        """Record an address range that runs past 65536."""
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


def paired_request(request: Pdu | None, fc: int) -> Pdu | None:
    """``request`` when it is a request of ``fc`` (context for its answer), else ``None``."""
    if request is not None and request.fc == fc and request.kind is Kind.REQUEST:
        return request
    return None


Decoder = Callable[[Out, Pdu | None], None]
"""A field decoder: fills the collector from its bytes, the paired request as context."""
