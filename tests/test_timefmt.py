"""One time basis: -t modes, the automatic date, any float
prints, and --since/--until accept every form a mode prints."""

from __future__ import annotations

import argparse
import datetime as dt
import math
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.timefmt import (
    CALENDAR_MAX,
    CALENDAR_MIN,
    TIME_MODES,
    TimeFormat,
    TimeParseError,
    add_time_option,
    epoch_text,
    human_span,
    parse_when,
    replace_time,
)

# 2024-05-01 12:00:05.123456 UTC
T0 = dt.datetime(2024, 5, 1, 12, 0, 5, 123456, tzinfo=dt.UTC).timestamp()

IMPOSSIBLE = [
    1e17,  # pcapng with a 1 s resolution and a mutated timestamp
    1.8e19,
    1.7e12,  # a nanosecond capture read as microseconds (year 55840)
    -1e12,
    -62135596800.0 - 5,  # before year 1
    253402300800.0 + 5,  # after 9999
    float("nan"),
    float("inf"),
    float("-inf"),
    2.0**63,
    -(2.0**63),
    1e308,
]


def local_clock(ts: float) -> str:
    return time.strftime("%H:%M:%S", time.localtime(int(ts)))


def test_each_mode_prints_its_form() -> None:
    assert TimeFormat("a").text(T0) == local_clock(T0) + ".123456"
    local_day = time.strftime("%Y-%m-%d", time.localtime(int(T0)))
    assert TimeFormat("ad").text(T0) == f"{local_day} {local_clock(T0)}.123456"
    assert TimeFormat("u").text(T0) == "12:00:05.123456"
    assert TimeFormat("ud").text(T0) == "2024-05-01 12:00:05.123456"
    assert TimeFormat("e").text(T0) == "1714564805.123456"
    rel = TimeFormat("r")
    assert rel.text(T0) == "0.000000"  # the first time printed is the origin
    assert rel.text(T0 + 12.5) == "12.500000"
    assert TimeFormat("r", origin=T0 - 1.123456).text(T0) == "1.123456"
    assert TimeFormat("u").bytes(T0) == b"12:00:05.123456"
    with pytest.raises(ValueError, match="unknown time format"):
        TimeFormat("x")


def test_the_date_shows_when_a_capture_spans_more_than_one_day() -> None:
    streaming = TimeFormat("u")
    assert streaming.text(T0) == "12:00:05.123456"
    assert streaming.text(T0 + 86400) == "2024-05-02 12:00:05.123456"  # another day
    assert streaming.text(T0 + 1) == "12:00:06.123456"  # the first day: no date
    span = TimeFormat.for_span("u", T0, T0 + 86400)
    assert span.text(T0) == "2024-05-01 12:00:05.123456"  # every line dated
    one_day = TimeFormat.for_span("u", T0, T0 + 3600)
    assert one_day.text(T0 + 60) == "12:01:05.123456"
    assert TimeFormat("u", auto_date=False).text(T0 + 5 * 86400) == "12:00:05.123456"


@pytest.mark.parametrize("mode", TIME_MODES)
@pytest.mark.parametrize("ts", IMPOSSIBLE)
def test_any_float_prints_in_every_mode(mode: str, ts: float) -> None:
    for fmt in (TimeFormat(mode), TimeFormat(mode, origin=T0), TimeFormat(mode, origin=ts)):
        text = fmt.text(ts)
        assert text and fmt.bytes(ts) == text.encode()
        assert "  " not in text
        if mode != "r" and math.isfinite(ts):
            assert float(text) == pytest.approx(ts, rel=1e-6)  # epoch seconds


@settings(max_examples=500, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(TIME_MODES))
def test_fuzz_time_text_never_raises(ts: float, mode: str) -> None:
    fmt = TimeFormat(mode)
    assert fmt.text(ts) == fmt.bytes(ts).decode()
    human_span(ts)
    epoch_text(ts)


@settings(max_examples=300, deadline=None)
@given(
    st.floats(min_value=0, max_value=3 * 86400),
    st.sampled_from(TIME_MODES),
    st.floats(min_value=0, max_value=2e9),
)
def test_since_until_accept_every_printed_form(offset: float, mode: str, start: float) -> None:
    ts = start + offset
    fmt = TimeFormat(mode, origin=start)
    text = fmt.text(ts)
    back = parse_when(text, start, fmt)
    assert abs(back - ts) <= 1.5e-6 * max(1.0, abs(ts) / 1e9), (mode, text)


def test_parse_fallback_and_explicit_forms() -> None:
    assert parse_when("100000000000000000.000000", T0) == 1e17
    assert parse_when("1.000000e+17", T0) == 1e17
    assert parse_when("-1000000000000.000000", T0) == -1e12
    assert parse_when("2024-05-01 12:00:05.5Z", T0) == pytest.approx(T0 + 0.376544)
    utc = TimeFormat("u")
    assert parse_when("12:00:05.123456", T0, utc) == pytest.approx(T0)
    assert parse_when("2024-05-01 12:00:05.123456", T0, utc) == pytest.approx(T0)
    assert parse_when("5", T0, TimeFormat("r")) == T0 + 5
    assert parse_when("-5", T0, TimeFormat("r")) == T0 - 5
    assert parse_when("5", T0, TimeFormat("e")) == 5.0
    assert parse_when("+5s", T0, TimeFormat("e")) == T0 + 5
    for bad in ("", "yesterday", "12:99:00"):
        with pytest.raises(TimeParseError):
            parse_when(bad, T0)


def test_human_span() -> None:
    assert human_span(7392.5) == "2 h 03 min 12.5 s"
    assert human_span(12.5) == "12.5 s"
    assert human_span(0.25) == "250 ms"
    assert human_span(0.0) == "0 ms"
    assert human_span(182.25) == "3 min 02.25 s"
    assert human_span(3 * 86400 + 600) == "3 d 00 h 10 min 00 s"
    assert human_span(1e17) == "1e+17 s"
    assert human_span(float("nan")) == "nan s"


def test_replace_time_swaps_only_a_printed_time() -> None:
    line = "12:00:05.123456  10.0.0.1:1 → 10.0.0.2:502  [u1 t1]  03 00 00 00 01  | x"
    assert replace_time(line, "0.000000") == line.replace("12:00:05.123456", "0.000000")
    dated = "2024-05-02 12:00:05.123456  -- Connect"
    assert replace_time(dated, "7.5") == "7.5  -- Connect"
    assert replace_time("#12  bus.bin  [u1]  03", "x") == "#12  bus.bin  [u1]  03"
    assert replace_time("1.000000e+17  -- y", "z") == "z  -- y"


def test_add_time_option() -> None:
    parser = argparse.ArgumentParser()
    add_time_option(parser)
    assert parser.parse_args([]).time_format == "a"
    assert parser.parse_args(["-t", "ud"]).time_format == "ud"
    with pytest.raises(SystemExit):
        parser.parse_args(["-t", "x"])


def test_calendar_bounds_are_inside_what_datetime_shows() -> None:
    for ts in (CALENDAR_MIN, CALENDAR_MAX - 1):
        dt.datetime.fromtimestamp(ts, dt.UTC)
        assert TimeFormat("ud").text(ts)[:4].isdigit()
