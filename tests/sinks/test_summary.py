"""The run summary's counts and time span."""

from __future__ import annotations

from mbmon.hub import Hub
from mbmon.model import Chunk, Direction, Event, EventKind, Transport
from mbmon.pipeline import Pipeline
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response
from mbmon.sinks.summary import Summary


def test_a_closing_stats_event_is_counted_but_not_part_of_the_time_span() -> None:
    """sniff ends with a STATS event (the kernel's drop counters) stamped when the
    capture stopped: the span is the traffic's, first frame to last."""
    summary = Summary()
    hub = Hub(Pipeline(), [summary])
    stream = hub.new_stream(Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")
    request = encode_adu(1, 1, encode_read_request(3, 0, 2))
    hub.feed(Chunk(100.0, stream, Direction.C2S, request))
    hub.feed(Chunk(100.5, stream, Direction.S2C, encode_adu(1, 1, encode_read_response(3, [1, 2]))))
    hub.feed(Event(160.0, None, EventKind.STATS, {"kernel_drops": 0, "complete": True}))
    hub.finish()
    assert summary.events["stats"] == 1
    assert (summary.first, summary.last) == (100.0, 100.5)
    assert "time span: 500 ms" in summary.text()


def _command_records(phases: list[tuple[int, str]]) -> list:
    from mbmon.model import CommandUpdate, Phase, Record, RecordKind, Stream

    stream = Stream(0, Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")
    return [
        Record(
            i,
            float(i),
            RecordKind.COMMAND,
            stream,
            command=CommandUpdate(float(i), stream, unit, Phase(phase), "PTP {A1 90}", 0),
        )
        for i, (unit, phase) in enumerate(phases)
    ]


def test_each_robot_command_is_counted_once_by_its_final_outcome() -> None:
    summary = Summary()
    steps = [
        (1, "written"), (1, "executing"), (1, "success"), (1, "returned"),  # one success
        (1, "written"), (1, "written"), (1, "executing"), (1, "fail"),  # one fail
        (2, "executing"),  # unit 2: executed, then executed again before a status
        (2, "executing"), (2, "warning"), (2, "success"),
        (1, "written"),  # the last block is never executed
    ]  # fmt: skip
    summary.on_records(_command_records(steps))
    assert summary.command_counts() == {
        "success": 2,
        "fail": 1,
        "executing, no status": 1,
        "written, not executed": 1,
    }
    assert (
        "robot commands: 5 (2 success, 1 fail, 1 executing, no status, 1 written, not executed);"
        " 1 warning" in summary.text()
    )


def test_a_captured_ptp_is_one_command_not_three() -> None:
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", "captures/hrss_ptp.pcap", "--profile", "hrss"],
        capture_output=True, text=True, timeout=120, cwd=repo,
    )  # fmt: skip
    assert "robot commands: 1 (1 success)\n" in out.stderr
