"""The proxy's observer: bounded backlog towards the hub, and batches per loop iteration."""

from __future__ import annotations

from typing import Any

from mbmon.model import Direction, Event, EventKind, Stream, Transport
from mbmon.proxy.config import ProxyStats, endpoint
from mbmon.proxy.observer import Observer

STREAM = Stream(0, Transport.TCP, "127.0.0.1:40000", "10.0.0.1:502")


class Taken:
    """A meter: the items the hub has taken (``Hub.seen``)."""

    seen = 0


def new_stream(t: Transport, c: str, s: str) -> Stream:
    return Stream(1, t, c, s)


def test_chunks_skipped_while_the_hub_is_behind_then_reported() -> None:
    got: list[Any] = []
    meter = Taken()
    obs = Observer(got.append, new_stream, meter=meter, max_backlog=3, clock=lambda: 5.0)
    for i in range(10):
        obs.chunk(STREAM, Direction.C2S, bytes([i]), float(i))
    # the hub took nothing: 4 went out (sent - seen > 3 stops the 5th), 6 skipped
    assert [c.data for c in got] == [bytes([i]) for i in range(4)]
    assert obs.skipped == 6
    obs.event(STREAM, EventKind.CONNECT, {})  # events always go through
    assert isinstance(got[-1], Event) and got[-1].kind is EventKind.CONNECT
    meter.seen = len(got)  # the hub catches up
    obs.chunk(STREAM, Direction.S2C, b"\xff", 11.0)
    notice, chunk = got[-2], got[-1]
    assert notice.kind is EventKind.NOTICE
    assert notice.info["message"].startswith("6 chunks were forwarded but not observed")
    assert chunk.data == b"\xff"


def test_batches_are_handed_over_once_per_loop_iteration_in_order() -> None:
    soon: list[Any] = []
    submitted: list[Any] = []
    obs = Observer(lambda item: None, new_stream, clock=lambda: 1.0)
    obs.bind(soon.append, submitted.append)
    obs.chunk(STREAM, Direction.C2S, b"a", 1.0)
    obs.event(STREAM, EventKind.NOTICE, {"message": "x"})
    obs.chunk(STREAM, Direction.S2C, b"b", 2.0)
    assert len(soon) == 1 and submitted == []  # one flush scheduled, nothing sent yet
    soon.pop()()
    assert len(submitted) == 1
    items = submitted[0]()
    assert [type(i).__name__ for i in items] == ["Chunk", "Event", "Chunk"]
    assert items[0].data == b"a" and items[2].data == b"b"
    obs.flush()  # nothing waiting: nothing sent
    assert len(submitted) == 1


def test_bound_without_a_submit_items_go_to_put_one_by_one() -> None:
    """The engine always binds its handover timer; an observer given no ``submit``
    (no hub batches) still puts every item at once, and schedules nothing."""
    got: list[Any] = []
    soon: list[Any] = []
    obs = Observer(got.append, new_stream, clock=lambda: 1.0)
    obs.bind(soon.append)
    obs.chunk(STREAM, Direction.C2S, b"a", 1.0)
    obs.event(STREAM, EventKind.NOTICE, {"message": "x"})
    assert [type(i).__name__ for i in got] == ["Chunk", "Event"] and soon == []


def test_endpoint_text_and_summary() -> None:
    assert endpoint("10.0.0.1", 502) == "10.0.0.1:502"
    assert endpoint("::1", 1502) == "[::1]:1502"
    stats = ProxyStats(clients=2, requests=5, responses=3, exceptions_0a=1, guard_refusals=1)
    text = stats.summary()
    assert "requests 5, responses 3" in text
    assert "exceptions made by the proxy 2 (0x0A 1, 0x0B 0, guard 1)" in text
