"""Record filters: one implementation for live records (``read``)
and logged JSON objects (``replay``/``export``); options shared by both commands."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent / "sinks"))
from sink_records import run_pipeline, session_items

from mbmon.filters import (
    FilterError,
    RecordFilter,
    add_filter_options,
    build_filter,
    parse_fcs,
    parse_range,
    parse_units,
    touches,
)
from mbmon.format import View, record_line, record_to_json
from mbmon.model import Record
from mbmon.timefmt import TimeFormat

RECORDS = [x for x in run_pipeline(session_items()) if isinstance(x, Record)]
VIEW = View()
START = RECORDS[0].ts

FILTERS = [
    RecordFilter(),
    RecordFilter(units=frozenset({1})),
    RecordFilter(units=frozenset({2})),
    RecordFilter(fcs=parse_fcs("3")),
    RecordFilter(fcs=parse_fcs("6,0x10")),
    RecordFilter(address=parse_range("0-1")),
    RecordFilter(address=parse_range("200")),
    RecordFilter(address=parse_range("1")),
    RecordFilter(grep="noise"),
    RecordFilter(grep="READ HOLDING"),
    RecordFilter(since=START + 0.02),
    RecordFilter(until=START + 0.02),
    RecordFilter(units=frozenset({1}), fcs=parse_fcs("3"), since=START + 0.01),
]


@pytest.mark.parametrize("flt", FILTERS, ids=repr)
def test_live_records_and_logged_objects_filter_alike(flt: RecordFilter) -> None:
    """The same filter keeps the same records whether it sees them live or as logged."""
    assert any(r.frame is not None for r in RECORDS) and any(r.event for r in RECORDS)
    live = [r.index for r in RECORDS if flt.matches_record(r, record_line(r, VIEW))]
    logged = []
    for r in RECORDS:
        obj = record_to_json(r, VIEW)
        if flt.matches(obj, obj["line"], r.ts):
            logged.append(r.index)
    assert live == logged
    if flt.active:
        assert 0 < len(live) < len(RECORDS) or flt.units == frozenset({2})


def test_frame_filters_drop_events_and_need_a_line_for_grep() -> None:
    event = next(r for r in RECORDS if r.event is not None)
    assert RecordFilter().matches_record(event)
    assert not RecordFilter(units=frozenset({1})).matches_record(event)
    assert RecordFilter(grep="x").needs_line and not RecordFilter().needs_line
    with pytest.raises(ValueError, match="grep"):
        RecordFilter(grep="x").matches_record(event)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    add_filter_options(p)
    return p


def test_options_build_the_filter() -> None:
    args = parser().parse_args(
        ["--unit", "1,2", "--unit", "3", "--fc", "3,0x10", "--address", "0x10-0x20",
         "--grep", "PTP", "--since", "+1s", "--until", "12:00:05"]
    )  # fmt: skip
    flt = build_filter(args, 1714564800.0, TimeFormat("u"))
    assert flt.units == frozenset({1, 2, 3}) and flt.fcs == frozenset({3, 16})
    assert flt.address == (16, 32) and flt.grep == "PTP"
    assert flt.since == 1714564801.0 and flt.until == 1714564805.0  # UTC with -t u


def test_times_of_a_capture_not_yet_read_resolve_at_the_first_record() -> None:
    args = parser().parse_args(["--since", "+0.02s"])
    flt = build_filter(args, start_known=False)
    assert flt.since is None and flt.since_text == "+0.02s"
    kept = [r.index for r in RECORDS if flt.matches_record(r, record_line(r, VIEW))]
    assert kept == [r.index for r in RECORDS if r.ts >= START + 0.02]
    with pytest.raises(FilterError):  # checked when built, not at the first record
        build_filter(parser().parse_args(["--since", "yesterday"]), start_known=False)


def test_bad_values_are_filter_errors() -> None:
    for bad in ("", "x", "0x"):
        with pytest.raises(FilterError):
            parse_fcs(bad)
    for bad in ("300-200", "-1", "70000", "a-b"):
        with pytest.raises(FilterError):
            parse_range(bad)
    with pytest.raises(FilterError, match=r"0\.\.255"):
        parse_units(["256"])
    assert touches({"address": 200, "count": 2}, 201, 300)
    assert not touches({"address": None}, 0, 65535)


def test_replay_keeps_its_old_names() -> None:
    """``mbmon.io.replay`` re-exports the filters (their home is mbmon.filters)."""
    import mbmon.filters as filters
    from mbmon.io import replay

    for name in ("RecordFilter", "FilterError", "Pacer", "parse_when", "touches", "iter_filtered"):
        assert getattr(replay, name) is getattr(filters, name)
