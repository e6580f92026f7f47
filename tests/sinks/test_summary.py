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
