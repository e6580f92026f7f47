"""Word helpers against the manual's own numbers (Appendix II, §5.4.4)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.semantics.words import (
    f32_to_u32,
    join_f32,
    join_i32,
    join_u32,
    s16,
    split_i32,
    split_u32,
    swap_word,
    u16,
    u32_to_f32,
)


@pytest.mark.parametrize(
    ("u", "s"), [(0, 0), (32767, 32767), (32768, -32768), (65535, -1), (37856, -27680)]
)
def test_s16_u16(u: int, s: int) -> None:
    assert s16(u) == s
    assert u16(s) == u
    assert s16(s) == s  # signed input passes through
    assert u16(u) == u


@pytest.mark.parametrize(
    ("low", "high", "value"),
    [
        (25294, 1, 90830),  # Appendix II example 1: A1 = 90.830 degrees
        (-6742, -7, -399958),  # Appendix II example 2: X = -399.958 mm
        (u16(-6742), u16(-7), -399958),  # same words as the wire carries them
        (-27680, 4, 300000),
        (27680, -5, -300000),
    ],
)
def test_join_i32_appendix_ii(low: int, high: int, value: int) -> None:
    assert join_i32(low, high) == value


@pytest.mark.parametrize(
    ("value", "words"),
    [(300000, (-27680, 4)), (-300000, (27680, -5)), (90830, (25294, 1)), (-399958, (-6742, -7))],
)
def test_split_i32_appendix_ii(value: int, words: tuple[int, int]) -> None:
    assert split_i32(value) == words


def test_table_46_example_words() -> None:
    # Table 46 (LIN example): R203 = 27680 for X = -300 mm, R205 = -27680 for Y = 300 mm
    assert split_i32(-300 * 1000)[0] == 27680
    assert split_i32(300 * 1000)[0] == -27680


@given(st.integers(min_value=-(2**31), max_value=2**31 - 1))
@settings(max_examples=200, deadline=None)
def test_i32_round_trip(value: int) -> None:
    low, high = split_i32(value)
    assert -32768 <= low <= 32767 and -32768 <= high <= 32767
    assert join_i32(low, high) == value
    assert join_u32(*split_u32(value)) == value & 0xFFFFFFFF


def test_ieee754() -> None:
    assert f32_to_u32(10.5) == 1093140480
    assert u32_to_f32(1093140480) == 10.5
    low, high = split_u32(1093140480)
    assert join_f32(low, high) == 10.5


@given(st.floats(width=32, allow_nan=False))
@settings(max_examples=200, deadline=None)
def test_ieee754_round_trip(x: float) -> None:
    assert u32_to_f32(f32_to_u32(x)) == x


def test_ieee754_nan() -> None:
    assert math.isnan(u32_to_f32(0x7FC00000))


def test_swap_word() -> None:
    # §5.4.4.1: 10 -> 655360; 65535 -> 4294901760; array example 11 -> 720896
    assert swap_word(10) == 655360
    assert swap_word(65535) == 4294901760
    assert swap_word(11) == 720896
    assert swap_word(swap_word(0x12345678)) == 0x12345678
