"""16-bit register words and the wider numbers HRSS builds from them.

HRSS stores 32-bit values in two registers, low word first, high word second
(manual Appendix II). Words arrive from the decoder as unsigned 16-bit ints
(``Pdu.values``) but the manual prints them signed; every helper here accepts
either form. Floats use IEEE754 single precision (§5.4.4.2/3) and SWAP_WORD
exchanges the two 16-bit halves of a 32-bit value (§5.4.4.1).
"""

from __future__ import annotations

import struct

__all__ = [
    "f32_to_u32",
    "join_f32",
    "join_i32",
    "join_u32",
    "s16",
    "split_i32",
    "split_u32",
    "swap_word",
    "u16",
    "u32_to_f32",
]


def s16(u: int) -> int:
    """A 16-bit word as a signed value (-32768..32767); signed input passes through."""
    u &= 0xFFFF
    return u - 0x10000 if u & 0x8000 else u


def u16(s: int) -> int:
    """A 16-bit word as an unsigned value (0..65535); unsigned input passes through."""
    return s & 0xFFFF


def join_i32(low: int, high: int) -> int:
    """Signed 32-bit value from (low word, high word), as Appendix II computes it.

    ``join_i32(25294, 1) == 90830`` (A1 = 90.830 degrees);
    ``join_i32(-6742, -7) == -399958`` (X = -399.958 mm).
    """
    return s16(high) * 65536 + u16(low)


def join_u32(low: int, high: int) -> int:
    """Unsigned 32-bit value from (low word, high word)."""
    return (u16(high) << 16) | u16(low)


def split_i32(value: int) -> tuple[int, int]:
    """(low, high) signed 16-bit words of a signed 32-bit value, as Appendix II writes them.

    ``split_i32(300000) == (-27680, 4)``; ``split_i32(-300000) == (27680, -5)``.
    Values outside the 32-bit range wrap modulo 2**32.
    """
    high, low = divmod(value, 65536)  # floor division: remainder always 0..65535
    return s16(low), s16(high)


def split_u32(value: int) -> tuple[int, int]:
    """(low, high) unsigned 16-bit words of a 32-bit value."""
    value &= 0xFFFFFFFF
    return value & 0xFFFF, value >> 16


def f32_to_u32(x: float) -> int:
    """IEEE754 single-precision bit pattern of ``x`` (IEEE754_ENCODE): 10.5 -> 1093140480."""
    return int(struct.unpack(">I", struct.pack(">f", x))[0])


def u32_to_f32(u: int) -> float:
    """Float from an IEEE754 single-precision bit pattern (IEEE754_DECODE): 1093140480 -> 10.5."""
    return float(struct.unpack(">f", struct.pack(">I", u & 0xFFFFFFFF))[0])


def swap_word(v: int) -> int:
    """SWAP_WORD of §5.4.4.1: exchange the 16-bit halves of a 32-bit value (10 -> 655360)."""
    v &= 0xFFFFFFFF
    return ((v & 0xFFFF) << 16) | (v >> 16)


def join_f32(low: int, high: int) -> float:
    """Float stored in two registers, low word first (the HRSS word order)."""
    return u32_to_f32(join_u32(low, high))
