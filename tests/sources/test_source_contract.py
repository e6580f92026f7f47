"""The source contract (mbmon.sources.base): a toy source of each mode, defined here,
runs through the hub into ``read``'s listeners (console, summary); every point of the
contract (open before outputs, start, items, stop, stats, closing events, summary,
one-line open errors) has its check."""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Iterable, Iterator

import pytest

from mbmon.format import View
from mbmon.hub import Hub, Item
from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.pipeline import Pipeline
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response
from mbmon.sinks.console import ConsoleListener
from mbmon.sinks.summary import Summary
from mbmon.sources.base import BaseSource, Source, SourceError, run_sources


def conversation(stream: Stream, n: int, t0: float = 100.0) -> Iterator[Chunk]:
    """``n`` polls of holding register 0x0100 on ``stream``, answered 5 ms later."""
    for i in range(n):
        ts = t0 + i * 0.1
        req = encode_adu(i & 0xFFFF, 1, encode_read_request(3, 0x100, 1))
        resp = encode_adu(i & 0xFFFF, 1, encode_read_response(3, [i & 0xFFFF]))
        yield Chunk(ts, stream, Direction.C2S, req)
        yield Chunk(ts + 0.005, stream, Direction.S2C, resp)


class ToyFile(BaseSource):
    """A file source: a generated conversation, read as fast as it goes."""

    mode = "file"

    def __init__(self, polls: int, *, fail: str | None = None) -> None:
        super().__init__()
        self.name = "toy.bin"
        self.polls = polls
        self.fail = fail
        self.stream: Stream | None = None
        self.calls: list[str] = []

    def open(self, hub: Hub) -> None:
        if self.fail:
            raise SourceError(self.fail)
        super().open(hub)
        self.calls.append("open")
        self.stream = hub.new_stream(Transport.TCP, "10.0.0.1:40000", "10.0.0.2:502")

    def items(self) -> Iterable[Item]:
        self.calls.append("items")
        assert self.stream is not None
        return conversation(self.stream, self.polls)

    def stop(self) -> None:
        self.calls.append("stop")

    def closing(self, ts: float) -> list[Event]:
        self.calls.append("closing")
        return [Event(ts, None, EventKind.STATS, {"source": self.name, "polls": self.polls})]

    def summary(self) -> list[str]:
        return [f"{self.polls} polls generated"]


class ToyLive(BaseSource):
    """A live source: a thread puts a conversation into the hub, then ends the run."""

    mode = "live"
    name = "toy-live"

    def __init__(self, polls: int, *, end_run: bool = True, pause: float = 0.0) -> None:
        super().__init__()
        self.pause = pause  # between two puts (a line's rhythm)
        self.polls = polls
        self.end_run = end_run
        self.thread: threading.Thread | None = None
        self.stopped = threading.Event()
        self.sent = 0

    def open(self, hub: Hub) -> None:
        super().open(hub)
        self.stream = hub.new_stream(Transport.TCP, "10.0.0.1:40001", "10.0.0.2:502")

    def start(self) -> None:
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        hub = self.hub
        assert hub is not None
        # live: the reads' own times (the hub's loop ticks at the wall clock)
        for chunk in conversation(self.stream, self.polls, t0=time.time()):
            if self.stopped.is_set():
                return
            hub.put(chunk)
            self.sent += 1
            time.sleep(self.pause)
        if self.end_run:
            hub.stop()

    def stop(self) -> None:
        self.stopped.set()
        if self.thread is not None:
            self.thread.join(5)

    def stats(self) -> dict[str, int]:
        return {"chunks sent": self.sent}


class ToyStream(ToyFile):
    """A stream source: its items come slowly (a pipe); the hub ticks while it waits."""

    mode = "stream"

    def items(self) -> Iterable[Item]:
        def slow() -> Iterator[Item]:
            for i, chunk in enumerate(super(ToyStream, self).items()):
                if i == 2:
                    time.sleep(0.6)  # a stalled pipe: the listeners still get ticks
                yield chunk

        return slow()


class Ticks:
    """Counts the listeners' ticks."""

    def __init__(self) -> None:
        self.ticks: list[float] = []
        self.events: list[Event] = []

    def on_tick(self, now: float) -> None:
        self.ticks.append(now)

    def on_event(self, event: Event) -> None:
        self.events.append(event)


def read_listeners() -> tuple[io.StringIO, ConsoleListener, Summary]:
    out = io.StringIO()
    return out, ConsoleListener(out, View()), Summary()


def test_toy_sources_satisfy_the_protocol() -> None:
    for source in (ToyFile(1), ToyLive(1), ToyStream(1), BaseSource()):
        assert isinstance(source, Source)


def test_file_source_through_the_hub_into_reads_listeners() -> None:
    out, console, summary = read_listeners()
    ticks = Ticks()
    hub = Hub(Pipeline(), [console, summary, ticks])
    source = ToyFile(5)
    source.open(hub)
    run_sources(hub, [source], clock=lambda: 200.0)
    hub.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 11  # ten frames, then the closing STATS event
    assert lines[0].endswith("03 01 00 00 01  | Read Holding Registers 256")
    assert lines[-1].endswith("-- Stats: source=toy.bin, polls=5")
    assert summary.requests + summary.responses == 10
    assert source.calls == ["open", "items", "stop", "closing"]
    stats = [e for e in ticks.events if e.kind is EventKind.STATS]
    assert [(e.ts, e.info) for e in stats] == [(200.0, {"source": "toy.bin", "polls": 5})]
    assert source.summary() == ["5 polls generated"]


def test_open_failure_is_one_line_and_nothing_runs() -> None:
    source = ToyFile(1, fail="toy.bin: cannot open (No such file or directory)")
    with pytest.raises(SourceError, match=r"^toy.bin: cannot open \(No such file"):
        source.open(Hub())
    assert source.calls == []


def test_live_source_runs_in_the_hubs_loop_until_it_stops_the_hub() -> None:
    out, console, summary = read_listeners()
    hub = Hub(Pipeline(), [console, summary])
    source = ToyLive(20)
    source.open(hub)
    done = threading.Thread(target=run_sources, args=(hub, [source]), daemon=True)
    done.start()
    done.join(30)
    assert not done.is_alive()
    hub.close()
    assert summary.requests + summary.responses == 40
    assert len(out.getvalue().splitlines()) == 40
    assert source.stopped.is_set()
    assert source.stats() == {"chunks sent": 40}


def test_live_source_is_stopped_when_the_run_is_stopped_from_outside() -> None:
    hub = Hub(Pipeline())
    source = ToyLive(1_000_000, end_run=False, pause=0.001)
    source.open(hub)
    stop = threading.Event()
    runner = threading.Thread(target=run_sources, args=(hub, [source], stop), daemon=True)
    runner.start()
    time.sleep(0.3)
    stop.set()
    hub.stop()
    runner.join(30)
    assert not runner.is_alive()
    assert source.stopped.is_set()
    assert source.thread is not None and not source.thread.is_alive()


def test_stream_source_gets_ticks_while_it_waits() -> None:
    _out, console, summary = read_listeners()
    ticks = Ticks()
    hub = Hub(Pipeline(), [console, summary, ticks])
    source = ToyStream(3)
    source.open(hub)
    run_sources(hub, [source], clock=lambda: 300.0)
    hub.close()
    assert summary.requests + summary.responses == 6
    assert ticks.ticks, "no tick reached the listeners while the stream stalled"
    assert all(t <= 100.3 for t in ticks.ticks)  # at the capture's time, never the clock's


def test_several_file_sources_are_one_run() -> None:
    _out, console, summary = read_listeners()
    hub = Hub(Pipeline(), [console, summary])
    first, second = ToyFile(2), ToyFile(3)
    for source in (first, second):
        source.open(hub)
    run_sources(hub, [first, second])
    hub.close()
    assert summary.requests + summary.responses == 10
    assert first.stream is not None and second.stream is not None
    assert first.stream.id != second.stream.id


def test_a_run_ended_early_feeds_no_closing_events() -> None:
    hub = Hub(Pipeline())
    source = ToyFile(3)
    source.open(hub)
    hub.enough()  # -c reached before the end
    run_sources(hub, [source])
    assert "closing" not in source.calls
    assert "stop" in source.calls


def test_live_and_file_sources_do_not_mix() -> None:
    hub = Hub(Pipeline())
    with pytest.raises(ValueError, match="cannot be mixed"):
        run_sources(hub, [ToyFile(1), ToyLive(1)])


class LastWords(ToyLive):
    """A live source whose stop() delivers a last event (the proxy's engine reports
    its connections closed as it stops): it must reach the listeners."""

    def stop(self) -> None:
        super().stop()
        hub = self.hub
        assert hub is not None
        hub.put(Event(time.time(), None, EventKind.NOTICE, {"message": "last words"}))


def test_what_a_live_source_delivers_as_it_stops_is_not_lost() -> None:
    ticks = Ticks()
    hub = Hub(Pipeline(), [ticks])
    source = LastWords(1_000_000, end_run=False, pause=0.001)
    source.open(hub)
    stop = threading.Event()
    runner = threading.Thread(target=run_sources, args=(hub, [source], stop), daemon=True)
    runner.start()
    time.sleep(0.3)
    stop.set()
    hub.stop()
    runner.join(30)
    assert not runner.is_alive()
    assert [e.info["message"] for e in ticks.events if e.kind is EventKind.NOTICE] == ["last words"]
