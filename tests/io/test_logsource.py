"""The log as a source of a run: stored records through the hub, filtered and paced."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import sink_records as records

from mbmon.filters import Pacer, RecordFilter
from mbmon.format import View, record_line
from mbmon.hub import Hub
from mbmon.io.logsource import LogSource, StoredPipeline, run_stored
from mbmon.io.mcap.reader import McapLog
from mbmon.io.replay import logged_records
from mbmon.model import Record
from mbmon.sinks.base import SinkContext
from mbmon.sinks.console import ConsoleListener
from mbmon.sinks.mcap import McapSink
from mbmon.stored import StoredRecord
from mbmon.timefmt import TimeFormat

VIEW = View(robot="192.168.0.10")


@pytest.fixture()
def session_log(tmp_path: Path, session_stream: list) -> Path:
    path = tmp_path / "s.mcap"
    with McapSink(path, SinkContext(view=VIEW, source="x.pcap")) as sink:
        records.feed(sink, session_stream)
    return path


class FakeClock:
    """A Pacer's clock and sleep: time moves only by what the pacer sleeps."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


def test_the_console_prints_the_stored_lines_through_the_hub(
    session_log: Path, session_stream: list
) -> None:
    """Stored records pass the hub as they are; the console prints their lines, which
    are the lines the records had live (the same console, the same format)."""
    live = [record_line(r, VIEW) for r in session_stream if isinstance(r, Record)]
    out = io.StringIO()
    with McapLog(session_log) as log:
        fmt = VIEW.time_format
        with Hub(StoredPipeline(), [ConsoleListener(out, View(time_format=fmt))]) as hub:
            run_stored(hub, LogSource(log, fmt))
    assert out.getvalue().splitlines() == live
    assert hub.records == len(live) and not hub.failures


def test_filters_keep_what_they_match_and_times_print_in_the_format(session_log: Path) -> None:
    with McapLog(session_log) as log:
        stored = [r.stored() for r in logged_records(log)]
        start = stored[0].ts
        fmt = TimeFormat("r", origin=start)
        flt = RecordFilter(fcs=frozenset({3}))
        got = list(LogSource(log, fmt, flt).items())
    assert got and all(isinstance(r, StoredRecord) for r in got)
    assert [r.index for r in got] == [
        r.index for r in stored if r.obj is not None and r.obj.get("fc") == 3
    ]
    for record in got:
        assert record.text(fmt).startswith(fmt.text(record.ts) + "  ")
        assert record.json(fmt)["line"] == record.text(fmt)


def test_pacing_waits_for_each_record_at_its_due_time(session_log: Path) -> None:
    clock = FakeClock()
    with McapLog(session_log) as log:
        fmt = TimeFormat("a")
        pacer = Pacer(2.0, clock=clock.clock, sleep=clock.sleep)
        source = LogSource(log, fmt, pacer=pacer)
        assert source.mode == "stream"
        due = []
        for record in source.items():
            due.append((record.ts, clock.now))
    assert len(due) > 3 and clock.sleeps
    t0, c0 = due[0]
    for ts, at in due:
        assert at == pytest.approx(c0 + (ts - t0) / 2.0, abs=1e-6)  # out when due, not before


def test_a_redecode_is_paced_only_inside_since_until(session_log: Path) -> None:
    """Every raw item is fed (a request before --since pairs its answer), but only those
    inside the shown span wait: --since +Ns never sleeps through the first N seconds."""
    with McapLog(session_log) as log:
        items = list(LogSource(log, TimeFormat("a"), raw=True).items())
        times = sorted({item.ts for item in items})
        assert len(times) > 3
        since = times[len(times) // 2]
        clock = FakeClock()
        pacer = Pacer(1.0, clock=clock.clock, sleep=clock.sleep)
        source = LogSource(log, TimeFormat("a"), RecordFilter(since=since), pacer=pacer, raw=True)
        paced = list(source.items())
    assert paced == items
    assert sum(clock.sleeps) == pytest.approx(times[-1] - since, abs=1e-6)
