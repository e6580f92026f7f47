"""The latency's texts and double, computed in the core without the dtoa round trip.

A response's latency (ms) is written three ways: the line's ``(%.1f ms)``, ``--json``'s
``latency_ms`` (``round(x, 3)`` as orjson writes it) and the log's ``modbus.Frame``
``latency_ms`` double (``round(x, 3)``). The core computes them exactly in integer
arithmetic (``fixed_text``, ``round3_exact``) and asks CPython only where it proves
nothing (non-finite, |x| >= 2^40). These tests hold them to CPython's own results: on
random doubles, on adversarial values (exact ties, their binary neighbours, tiny,
negative, subnormal), and on every latency that microsecond and nanosecond capture
times give over a realistic span (the sweep runs in C against CPython's formatting).
"""

from __future__ import annotations

import math
import struct

import orjson
import pytest
from core_diff import require_core
from hypothesis import example, given, settings
from hypothesis import strategies as st

from mbmon import core

LIMIT = 2.0**40  # what the core proves: |x| below this, finite


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def _r() -> object:
    return core._reader


def _bits(x: float) -> bytes:
    return struct.pack("<d", x)


def check(x: float) -> None:
    """The core's texts and double of ``x`` are CPython's, or it declares them unproven."""
    r = _r()
    proven = math.isfinite(x) and abs(x) < LIMIT
    for prec in range(4):
        mine = r._fixed_text(x, prec)  # type: ignore[attr-defined]
        if not proven:
            assert mine is None, (x, prec)
            continue
        assert mine == format(x, f".{prec}f").encode(), (x, prec)
    rounded = r._round3(x)  # type: ignore[attr-defined]
    if not proven:
        assert math.isnan(rounded), x
        return
    assert _bits(rounded) == _bits(round(x, 3)), (x, rounded, round(x, 3))
    text = f"{x:.3f}".rstrip("0")
    text = text + "0" if text.endswith(".") else text
    assert r._json_round3(x) == text.encode(), x  # type: ignore[attr-defined]
    if abs(x) < 1e9:
        assert r._json_round3(x) == orjson.dumps(round(x, 3)), x  # type: ignore[attr-defined]


def _neighbours(x: float, ulps: int = 3) -> list[float]:
    out = [x]
    up = down = x
    for _ in range(ulps):
        up = math.nextafter(up, math.inf)
        down = math.nextafter(down, -math.inf)
        out += [up, down]
    return out


ADVERSARIAL = [
    0.0,
    -0.0,
    1e-4,
    -1e-4,
    5e-4,
    0.0005,
    0.0015,
    0.0625,  # exact ties of three decimals are the odd sixteenths
    0.1875,
    -0.0625,
    0.25,  # exact ties of one decimal: odd quarters
    0.75,
    2.5,  # ... and of none: odd halves
    999.9995,
    -999.9995,
    9.9995,
    0.9995,
    0.95,
    0.05,
    1.0005,
    123456.7895,
    5e-324,  # the smallest subnormal
    -5e-324,
    2.2250738585072014e-308,  # the smallest normal
    1e-300,
    LIMIT,  # outside: CPython's own
    math.nextafter(LIMIT, 0.0),
    -LIMIT,
    1e12,
    1e300,
    math.inf,
    -math.inf,
    math.nan,
]


@pytest.mark.parametrize("x", [y for a in ADVERSARIAL for y in _neighbours(a)])
def test_adversarial(x: float) -> None:
    check(x)


def test_halfway_neighbourhoods() -> None:
    """x.xxx5 and x.x5 as decimals (never exact in binary, a hair off each way) and the
    doubles next to them, over a spread of magnitudes."""
    for k in [*range(3000), 10**6 + 1, 10**9 + 7, 123456789]:
        for base in ((k + 0.5) / 1000, (k + 0.5) / 10, k + 0.5, (2 * k + 1) / 16):
            for x in _neighbours(base, 2):
                check(x)
                check(-x)


@settings(max_examples=400, deadline=None)
@given(st.floats(min_value=-1e7, max_value=1e7, allow_nan=False))
@example(999.9995)
def test_random_latencies(x: float) -> None:
    check(x)


@settings(max_examples=300, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True))
def test_random_doubles(x: float) -> None:
    check(x)


@settings(max_examples=200, deadline=None)
@given(st.integers(min_value=0, max_value=2**40 * 1000), st.integers(-4, 4))
def test_near_decimals(micro: int, ulps: int) -> None:
    """Doubles a few ulps from a value of three decimals or from its midpoint."""
    for base in (micro / 1000, (micro + 0.5) / 1000):
        x = base
        for _ in range(abs(ulps)):
            x = math.nextafter(x, math.inf if ulps > 0 else -math.inf)
        check(x)


def _sweep(*args: int, **kw: bool) -> None:
    checked, bad, first, unproven = _r()._latency_sweep(*args, **kw)  # type: ignore[attr-defined]
    assert unproven == 0
    assert bad == 0, f"{bad} of {checked} latencies differ from CPython's, first {first!r}"
    assert checked >= args[3]


def test_every_microsecond_for_ten_seconds() -> None:
    """Every latency of microsecond capture times from 0 to 10 s (a request at a
    late-2023 epoch time), and the first second the other way round."""
    _sweep(1_700_000_000, 123_456, 1_000_000, 10_000_001, negative=False)
    _sweep(1_700_000_000, 999_999, 1_000_000, 1_000_001)


def test_microseconds_elsewhere() -> None:
    """Other epochs and offsets: the start of time, a second boundary, 2106."""
    _sweep(0, 0, 1_000_000, 200_001)
    _sweep(86_399, 999_000, 1_000_000, 200_001)
    _sweep(4_294_967_295, 500_000, 1_000_000, 200_001)


def test_nanoseconds() -> None:
    """Nanosecond captures: every ns over 0.3 ms, then every 997 ns (a step that meets
    every residue) over 0.2 s, pcap (seconds + fraction) and pcapng (one stamp)."""
    _sweep(1_700_000_000, 123_456_789, 1_000_000_000, 300_001)
    _sweep(1_700_000_000, 123_456_789, 1_000_000_000, 200_001, 997)
    _sweep(1_700_000_000, 123_456_789, 1_000_000_000, 200_001, 997, pcapng=True)
    _sweep(1_700_000_000, 999_999_999, 1_000_000, 200_001, pcapng=True)
