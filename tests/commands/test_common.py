"""What every command shares (commands/common.py): the one exit status, the one signal
handling for commands that run until stopped, the one listener order and the one -c.

Real signals sent to this process, a real hub and pipeline over the project's own
capture (captures/hrss_ptp.pcap); no mocks.
"""

from __future__ import annotations

import asyncio
import os
import signal
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

import pytest

from mbmon.commands import ending
from mbmon.commands.common import (
    EXIT_BAD_INPUT,
    EXIT_OK,
    FrameBudget,
    attach_outputs,
    exit_status,
    loop_stops_on_signals,
    stop_on_signals,
)
from mbmon.filters import RecordFilter
from mbmon.format import View
from mbmon.hub import Hub
from mbmon.pipeline import Pipeline
from mbmon.sources.pcapfile import CaptureConfig, read_capture

REPO = Path(__file__).resolve().parents[2]
CAPTURE = REPO / "captures" / "hrss_ptp.pcap"


@pytest.fixture(autouse=True)
def no_signal_yet() -> Iterator[None]:
    """Each test starts and ends with no signal recorded (the record is per run)."""
    saved = list(ending._received)
    ending._received.clear()
    yield
    ending._received[:] = saved


class _Failing:
    name = "out.jsonl"

    def __init__(self, exc: Exception) -> None:
        self.exc = exc

    def on_records(self, records: list[Any]) -> None:
        raise self.exc


def _hub_with(exc: Exception | None = None, error: str | None = None) -> Hub:
    """A hub that ran over the capture, with a listener failing with ``exc``, and with
    ``error`` recorded as an input error."""
    hub = Hub(Pipeline())
    if isinstance(exc, BrokenPipeError):  # what the hub records (it would also quiet stdout)
        hub.failures.append(("stdout", "broken pipe"))
    elif exc is not None:
        hub.add_listener(_Failing(exc))
        hub.add_listener(_Collect())  # the run goes on: not every listener is gone
    hub.run_items(read_capture(CAPTURE, CaptureConfig()))
    if error is not None:
        hub.errors.append(error)
    hub.close()
    return hub


class _Collect:
    def __init__(self, log: list[tuple[str, int]] | None = None, name: str = "") -> None:
        self.records: list[Any] = []
        self.log = log
        self.name = name

    def on_records(self, records: list[Any]) -> None:
        self.records.extend(records)
        if self.log is not None:
            self.log.append((self.name, len(records)))


# --------------------------------------------------------------------------- exit status

#: (output failure, input error, interrupted, command failed, until signal) -> status
EXIT_TABLE = [
    (None, None, False, False, False, EXIT_OK),
    (BrokenPipeError(32, "Broken pipe"), None, False, False, False, EXIT_OK),  # | head
    (OSError(28, "No space left on device"), None, False, False, False, EXIT_BAD_INPUT),
    (OSError(28, "No space left on device"), None, True, False, False, EXIT_BAD_INPUT),
    (None, "damaged capture", False, False, False, EXIT_BAD_INPUT),
    (None, "damaged capture", True, False, False, 130),
    (None, None, True, False, False, 130),
    (None, None, True, False, True, EXIT_OK),  # sniff, proxy, servers: the normal end
    (None, None, False, True, False, EXIT_BAD_INPUT),
    (None, None, True, True, False, 130),
]


@pytest.mark.parametrize(("exc", "error", "interrupted", "failed", "until", "status"), EXIT_TABLE)
def test_one_exit_status(
    exc: Exception | None,
    error: str | None,
    interrupted: bool,
    failed: bool,
    until: bool,
    status: int,
) -> None:
    hub = _hub_with(exc, error)
    got = exit_status(hub, interrupted=interrupted, failed=failed, until_signal=until)
    assert got == status


def test_a_signal_recorded_is_an_interruption_even_if_the_command_never_saw_it() -> None:
    ending._received.append(signal.SIGTERM)
    assert exit_status(_hub_with()) == 143
    assert exit_status(_hub_with(), until_signal=True) == EXIT_OK


# --------------------------------------------------------------------------- signals


def test_stop_on_signals_calls_stop_counts_and_restores() -> None:
    before = signal.getsignal(signal.SIGINT)
    calls: list[int] = []
    with stop_on_signals(calls.append) as got:
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000):  # the handlers run between bytecodes of this thread
            if len(calls) == 2:
                break
    assert calls == [1, 2]
    assert got.received == [signal.SIGTERM, signal.SIGINT] and got.signum == signal.SIGTERM
    assert ending.received_signal() == signal.SIGTERM
    assert signal.getsignal(signal.SIGINT) is before


def test_loop_stops_on_signals_stops_the_loop_and_restores() -> None:
    before = signal.getsignal(signal.SIGTERM)

    async def main() -> list[int]:
        stop = asyncio.Event()
        calls: list[int] = []

        def on(n: int) -> None:
            calls.append(n)
            stop.set()

        with loop_stops_on_signals(asyncio.get_running_loop(), on):
            os.kill(os.getpid(), signal.SIGTERM)
            await asyncio.wait_for(stop.wait(), 10)
        return calls

    assert asyncio.run(main()) == [1]
    assert ending.received_signal() == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is before


# --------------------------------------------------------------------------- order and -c


def _records() -> list[Any]:
    hub = Hub(Pipeline())
    got = _Collect()
    hub.add_listener(got)
    hub.run_items(read_capture(CAPTURE, CaptureConfig()))
    hub.close()
    return got.records


def test_logs_then_screen_then_summary() -> None:
    """Whatever order a command builds them in, each batch reaches the logs first."""
    order: list[tuple[str, int]] = []
    hub = Hub(Pipeline())
    attach_outputs(
        hub,
        summary=_Collect(order, "summary"),
        screen=_Collect(order, "screen"),
        logs=[_Collect(order, "log1"), None, _Collect(order, "log2")],
    )
    hub.run_items(read_capture(CAPTURE, CaptureConfig()))
    hub.close()
    names = [name for name, _n in order]
    assert names[:4] == ["log1", "log2", "screen", "summary"]
    assert names == ["log1", "log2", "screen", "summary"] * (len(names) // 4)


def test_count_is_frames_that_pass_the_filters_and_every_output_ends_there() -> None:
    records = _records()
    assert records[0].frame is None  # the capture starts with the Connect event
    writes = [r for r in records if r.frame is not None and r.frame.pdu.fc == 16]
    assert len(writes) >= 3
    table = [
        (RecordFilter(), 5, [r for r in records if r.frame is not None][4]),
        (RecordFilter(fcs=frozenset({16})), 3, writes[2]),
    ]
    for flt, count, last in table:
        hub = Hub(Pipeline())
        stops: list[bool] = []
        log, screen = _Collect(), _Collect()
        budget = FrameBudget(count, partial(stops.append, True), flt, View())
        attach_outputs(hub, logs=[log], screen=screen, budget=budget)
        hub.run_items(read_capture(CAPTURE, CaptureConfig()))
        hub.close()
        assert stops == [True]
        assert log.records[-1] is not None and log.records[-1].index == last.index
        assert [r.index for r in screen.records] == [r.index for r in log.records]
        assert log.records[0].frame is None  # the Connect is shown, and not counted
