"""``Hub.feed`` and ``Hub.feed_items`` are one path: the same input, fed item by
item or in batches of any size, gives the same records, notices (with their
times), failures, errors and counters, failing listeners included."""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.hub import Hub
from mbmon.model import Chunk, Direction, Event, EventKind, Record, Stream, Transport
from mbmon.pipeline import Pipeline
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response

STREAM = Stream(0, Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")
OTHER = Stream(1, Transport.TCP, "10.0.0.3:50001", "10.0.0.2:502")


@dataclass
class Recorder:
    """Keeps every call in order, as comparable tuples; never fails."""

    name: str = "recorder"
    calls: list[tuple[Any, ...]] = field(default_factory=list)

    def on_chunk(self, chunk: Chunk) -> None:
        self.calls.append(("chunk", chunk))

    def on_event(self, event: Event) -> None:
        self.calls.append(("event", event))

    def on_records(self, records: list[Record]) -> None:
        self.calls.append(("records", tuple(records)))

    def on_tick(self, now: float) -> None:
        self.calls.append(("tick", now))

    def close(self) -> None:
        self.calls.append(("close",))


@dataclass
class Failing:
    """Raises in ``hook`` on its ``at``-th call of that hook (0-based)."""

    name: str
    hook: str
    at: int
    error: type[Exception]
    calls: int = 0
    closed: int = 0

    def _maybe_fail(self, hook: str) -> None:
        if hook == self.hook:
            if self.calls == self.at:
                self.calls += 1
                raise self.error(f"{self.name} broke in {hook}")
            self.calls += 1

    def on_chunk(self, chunk: Chunk) -> None:
        self._maybe_fail("on_chunk")

    def on_event(self, event: Event) -> None:
        self._maybe_fail("on_event")

    def on_record(self, record: Record) -> None:
        self._maybe_fail("on_record")

    def close(self) -> None:
        self.closed += 1


def _chunk_data(draw: Any) -> bytes:
    kind = draw(st.sampled_from(["request", "response", "junk"]))
    tid = draw(st.integers(0, 5))
    if kind == "request":
        return encode_adu(tid, 1, encode_read_request(3, draw(st.integers(0, 100)), 2))
    if kind == "response":
        return encode_adu(tid, 1, encode_read_response(3, [draw(st.integers(0, 0xFFFF)), 0]))
    return draw(st.binary(min_size=1, max_size=20))


@st.composite
def items(draw: Any) -> list[Chunk | Event]:
    """Random input: chunks (requests, responses, junk) both ways on two streams,
    connects, disconnects and stream-less errors, at times that mostly grow."""
    out: list[Chunk | Event] = []
    ts = 100.0
    for _ in range(draw(st.integers(0, 25))):
        ts += draw(st.sampled_from([0.0, 0.001, 0.5, 1.0, -0.25, 3.0]))
        stream = draw(st.sampled_from([STREAM, OTHER]))
        what = draw(st.sampled_from(["chunk"] * 6 + ["connect", "disconnect", "error"]))
        if what == "chunk":
            direction = draw(st.sampled_from([Direction.C2S, Direction.S2C]))
            out.append(Chunk(ts, stream, direction, _chunk_data(draw)))
        elif what == "connect":
            out.append(Event(ts, stream, EventKind.CONNECT))
        elif what == "disconnect":
            out.append(Event(ts, stream, EventKind.DISCONNECT, {"how": "fin", "by": "client"}))
        else:
            out.append(Event(ts, None, EventKind.ERROR, {"message": f"damaged at {ts}"}))
    return out


failing = st.builds(
    Failing,
    name=st.sampled_from(["a.log", "b.log"]),
    hook=st.sampled_from(["on_chunk", "on_event", "on_record"]),
    at=st.integers(0, 8),
    error=st.sampled_from([OSError, ValueError, RuntimeError]),
)


def _run(
    batches: list[list[Chunk | Event]], specs: list[Failing], one_by_one: bool
) -> tuple[Any, ...]:
    before, after = Recorder("before"), Recorder("after")
    broken = [Failing(f.name, f.hook, f.at, f.error) for f in specs]
    err = io.StringIO()
    hub = Hub(Pipeline(), [before, *broken, after], stderr=err)
    for batch in batches:
        if one_by_one:
            for item in batch:
                hub.feed(item)
        else:
            hub.feed_items(batch)
    hub.finish()
    hub.close()
    return (
        before.calls,
        after.calls,
        [(b.calls, b.closed) for b in broken],
        hub.failures,
        hub.errors,
        hub.now,
        hub.seen,
        hub.records,
        err.getvalue(),
    )


@settings(max_examples=150, deadline=None)
@given(
    data=items(),
    specs=st.lists(failing, max_size=3),
    cuts=st.lists(st.integers(0, 25), max_size=4),
)
def test_feed_and_feed_items_give_the_same_run(
    data: list[Chunk | Event], specs: list[Failing], cuts: list[int]
) -> None:
    bounds = sorted({0, len(data), *(c for c in cuts if c <= len(data))})
    batches = [data[a:b] for a, b in pairwise(bounds)]
    assert _run(batches, specs, one_by_one=True) == _run(batches, specs, one_by_one=False)


def test_a_detach_notice_is_stamped_with_the_failing_items_time_either_way() -> None:
    """The case that told the two copies apart: a listener failing on its second
    chunk (at 101.0) was reported at 100.0 by ``feed`` and 0.0 by ``feed_items``."""
    data: list[Chunk | Event] = [
        Chunk(100.0, STREAM, Direction.C2S, encode_adu(1, 1, encode_read_request(3, 0, 2))),
        Chunk(101.0, STREAM, Direction.S2C, encode_adu(1, 1, encode_read_response(3, [7, 0]))),
    ]
    spec = [Failing("a.log", "on_chunk", 1, OSError)]
    for one_by_one in (True, False):
        calls = _run([data], spec, one_by_one)[0]
        notices = [
            r
            for call in calls
            if call[0] == "records"
            for r in call[1]
            if r.event is not None and r.event.kind is EventKind.NOTICE
        ]
        assert [n.ts for n in notices] == [101.0], one_by_one
