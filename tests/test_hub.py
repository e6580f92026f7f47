"""The hub: records reach every listener, a failing one is detached and reported,
close runs on all of them (also on SIGINT/SIGTERM), time moves on while the line is
silent, and several sources never collide on stream ids."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

from mbmon.format import View
from mbmon.hub import Hub
from mbmon.model import Chunk, Direction, Event, EventKind, Record, RecordKind, Transport
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response
from mbmon.sinks.console import ConsoleListener

REPO = Path(__file__).resolve().parents[1]


class Collect:
    """A listener that keeps everything it is given."""

    def __init__(self) -> None:
        self.records: list[Record] = []
        self.chunks: list[Chunk] = []
        self.events: list[Event] = []
        self.ticks: list[float] = []
        self.closed = 0

    def on_chunk(self, chunk: Chunk) -> None:
        self.chunks.append(chunk)

    def on_event(self, event: Event) -> None:
        self.events.append(event)

    def on_record(self, record: Record) -> None:
        self.records.append(record)

    def on_tick(self, now: float) -> None:
        self.ticks.append(now)

    def close(self) -> None:
        self.closed += 1


class Explodes:
    """Raises on the n-th record (a full disk, a bug)."""

    name = "exploding.log"

    def __init__(self, after: int) -> None:
        self.after = after
        self.seen = 0
        self.closed = 0

    def on_record(self, record: Record) -> None:
        self.seen += 1
        if self.seen > self.after:
            raise OSError(28, "No space left on device", "exploding.log")

    def close(self) -> None:
        self.closed += 1


def polling(hub: Hub, polls: int, t0: float = 1000.0) -> list[Chunk | Event]:
    """A client polling a server: connect, ``polls`` request/response pairs."""
    stream = hub.new_stream(Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")
    items: list[Chunk | Event] = [Event(t0, stream, EventKind.CONNECT)]
    for tid in range(1, polls + 1):
        ts = t0 + tid * 0.1
        items.append(
            Chunk(ts, stream, Direction.C2S, encode_adu(tid, 1, encode_read_request(3, 0, 2)))
        )
        items.append(
            Chunk(
                ts + 0.01,
                stream,
                Direction.S2C,
                encode_adu(tid, 1, encode_read_response(3, [tid, 0])),
            )
        )
    return items


def test_every_listener_gets_every_record_chunk_and_event() -> None:
    a, b = Collect(), Collect()
    hub = Hub(Pipeline(), [a, b])
    items = polling(hub, 10)
    hub.run_items(items)
    hub.close()
    kinds = [r.kind for r in a.records]
    assert kinds.count(RecordKind.REQUEST) == kinds.count(RecordKind.RESPONSE) == 10
    assert [r.index for r in a.records] == [r.index for r in b.records]
    assert len(a.chunks) == 20 and [e.kind for e in a.events] == [EventKind.CONNECT]
    assert a.closed == b.closed == 1
    hub.close()
    assert a.closed == 1  # close is idempotent


def test_a_failing_listener_is_detached_and_reported_while_the_others_get_everything() -> None:
    good, bad, after = Collect(), Explodes(after=5), Collect()
    err = io.StringIO()
    hub = Hub(Pipeline(), [good, bad, after], stderr=err)
    hub.run_items(polling(hub, 20))
    hub.close()
    frames = [r for r in good.records if r.frame is not None]
    assert len(frames) == 40 and len([r for r in after.records if r.frame is not None]) == 40
    assert bad.seen == 6 and bad.closed == 1  # closed once, at the failure
    assert hub.failures == [("exploding.log", "exploding.log: No space left on device")]
    assert err.getvalue().count("No space left on device") == 1  # reported once
    notices = [r for r in good.records if r.event is not None and r.event.kind is EventKind.NOTICE]
    assert len(notices) == 1 and "detached" in notices[0].event.info["message"]
    assert bad not in hub.listeners and good in hub.listeners


def test_a_failing_close_does_not_keep_the_others_from_closing() -> None:
    class BadClose(Collect):
        def close(self) -> None:
            super().close()
            raise ValueError("cannot finish")

    first, second = BadClose(), Collect()
    err = io.StringIO()
    hub = Hub(Pipeline(), [first, second], stderr=err)
    hub.run_items(polling(hub, 2))
    hub.close()
    assert first.closed == second.closed == 1
    assert "cannot finish" in err.getvalue()


def test_hooks_are_called_only_where_defined() -> None:
    class OnlyClose:
        closed = False

        def close(self) -> None:
            self.closed = True

    class OnlyBatches:
        def __init__(self) -> None:
            self.batches: list[list[Record]] = []

        def on_records(self, records: list[Record]) -> None:
            self.batches.append(records)

        def on_record(self, record: Record) -> None:  # the batch hook wins
            raise AssertionError("on_record called although on_records exists")

    only_close, batches = OnlyClose(), OnlyBatches()
    hub = Hub(Pipeline(), [only_close, batches])
    hub.run_items(polling(hub, 3))
    hub.close()
    assert only_close.closed and sum(len(b) for b in batches.batches) >= 6
    assert not hub.failures


def test_stream_ids_from_many_threads_never_collide() -> None:
    hub = Hub(Pipeline())
    ids: list[int] = []
    lock = threading.Lock()

    def take() -> None:
        mine = [hub.new_stream(Transport.RTU, "a", "a").id for _ in range(500)]
        with lock:
            ids.extend(mine)

    threads = [threading.Thread(target=take) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(ids) == list(range(4000))


def test_live_unanswered_request_is_reported_at_its_timeout_without_more_input() -> None:
    """A live source sends one request and then nothing: the hub's clock reports it."""
    got = Collect()
    hub = Hub(Pipeline(config=PipelineConfig(timeout=0.3)), [got])
    stream = hub.new_stream(Transport.TCP, "127.0.0.1:40000", "127.0.0.1:1502")
    sent = time.time()
    request = encode_adu(7, 1, encode_read_request(3, 0, 2))

    def source() -> None:  # a source thread, as pyserial's or scapy's reader
        hub.put(Chunk(sent, stream, Direction.C2S, request))

    threading.Thread(target=source).start()
    stop = threading.Event()
    threading.Timer(1.5, stop.set).start()
    hub.run(stop)
    timeouts = [r for r in got.records if r.event and r.event.kind is EventKind.TIMEOUT]
    assert len(timeouts) == 1
    # at the timeout (stamped when due: sent + 0.3, to float rounding), not at the end
    assert 0.3 - 1e-6 <= timeouts[0].ts - sent < 0.3 + 0.6
    assert got.ticks, "listeners get on_tick while the line is silent"


def test_submit_runs_producers_in_the_hub_thread() -> None:
    got = Collect()
    hub = Hub(Pipeline(), [got])
    threads: list[str] = []
    items = polling(hub, 2)

    def producer() -> list[Chunk | Event]:
        threads.append(threading.current_thread().name)
        return items

    threading.Thread(target=lambda: hub.submit(producer)).start()
    time.sleep(0.2)
    hub.run(until_idle=True)
    assert threads == [threading.current_thread().name]
    assert len([r for r in got.records if r.frame is not None]) == 4


def test_seen_counts_every_item_taken_singly_or_in_batches_and_the_run_goes_on() -> None:
    """``Hub.seen`` is the live sources' backlog meter (the proxy's observer): every
    chunk and event fed, one by one or in a submitted batch; a batch does not
    finish the pipeline (a request of one batch is answered in the next)."""
    got = Collect()
    hub = Hub(Pipeline(), [got])
    items = polling(hub, 3)
    hub.feed(items[0])
    assert hub.seen == 1
    hub.submit(lambda: items[1:4])  # ends on a request: its answer comes next
    hub.submit(lambda: items[4:])
    hub.run(until_idle=True)
    assert hub.seen == len(items) == 7
    frames = [r for r in got.records if r.frame is not None]
    assert len(frames) == 6
    assert all(r.request is not None for r in frames if r.frame.direction is Direction.S2C)


def test_console_lines_are_flushed_within_half_a_second_on_an_idle_stream() -> None:
    """Not live (blocks of 512 lines), yet a lone line shows up within 0.5 s."""
    r_fd, w_fd = os.pipe()
    out = io.TextIOWrapper(io.FileIO(w_fd, "w"), encoding="utf-8", newline="\n")
    hub = Hub(Pipeline(), [ConsoleListener(out, View(), live=False)])
    stream = hub.new_stream(Transport.TCP, "127.0.0.1:40000", "127.0.0.1:1502")
    stop = threading.Event()
    runner = threading.Thread(target=hub.run, args=(stop,))
    runner.start()
    start = time.monotonic()
    hub.put(
        Chunk(time.time(), stream, Direction.C2S, encode_adu(1, 1, encode_read_request(3, 0, 1)))
    )
    os.set_blocking(r_fd, False)
    data = b""
    while b"\n" not in data and time.monotonic() - start < 2.0:
        try:
            data += os.read(r_fd, 4096)
        except BlockingIOError:
            time.sleep(0.01)
    elapsed = time.monotonic() - start
    stop.set()
    runner.join(timeout=5)
    hub.close()
    os.close(r_fd)
    assert b"03 00 00 00 01" in data
    assert elapsed < 0.5 + 0.1


_SCRIPT = textwrap.dedent(
    """
    import sys, threading
    from mbmon.commands.common import install_signal_handlers, interrupted_status
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline

    class Mark:
        def __init__(self, path):
            self.path = path
        def close(self):
            open(self.path, "w").write("closed")

    class Boom:
        def on_tick(self, now):
            raise RuntimeError("broken listener")

    install_signal_handlers()
    hub = Hub(Pipeline(), [Boom(), Mark(sys.argv[1]), Mark(sys.argv[2])])
    print("ready", flush=True)
    try:
        with hub:
            hub.run()
    except KeyboardInterrupt:  # SIGINT and SIGTERM alike (one handler)
        sys.exit(interrupted_status())
    """
)


def _run_until_signal(tmp_path: Path, sig: int) -> tuple[int, list[str], str]:
    marks = [tmp_path / f"{sig}-a", tmp_path / f"{sig}-b"]
    proc = subprocess.Popen(
        [sys.executable, "-c", _SCRIPT, *map(str, marks)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    time.sleep(0.6)  # the broken listener has failed by now
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=30)
    return proc.returncode, [m.read_text() if m.exists() else "" for m in marks], stderr


def test_close_runs_on_every_listener_after_an_error_and_on_sigint(tmp_path: Path) -> None:
    code, marks, stderr = _run_until_signal(tmp_path, signal.SIGINT)
    assert marks == ["closed", "closed"]
    assert "broken listener" in stderr and "Traceback" not in stderr
    assert code == 128 + signal.SIGINT


def test_close_runs_on_every_listener_on_sigterm(tmp_path: Path) -> None:
    code, marks, stderr = _run_until_signal(tmp_path, signal.SIGTERM)
    assert marks == ["closed", "closed"]
    assert code == 128 + signal.SIGTERM
    assert "Traceback" not in stderr


def test_every_hook_is_optional_for_the_hub_and_for_every_wrapper() -> None:
    """One contract: a listener with no hook at all, or with ``on_record`` only, works
    behind the hub and behind each wrapper that composes hooks with ``hooks_of``."""
    from mbmon.analysis.trigger import TriggerGate
    from mbmon.commands.common import FrameBudget, Limited
    from mbmon.filters import parse_expression
    from mbmon.hub import HOOKS, hooks_of
    from mbmon.sinks.select import Selection

    class Bare:
        pass

    class OnlyRecord:
        def __init__(self) -> None:
            self.records: list[Record] = []

        def on_record(self, record: Record) -> None:
            self.records.append(record)

    assert all(getattr(hooks_of(Bare()), hook) is None for hook in HOOKS)
    hooks = hooks_of(Collect())
    assert all(getattr(hooks, hook) is not None for hook in HOOKS if hook != "on_records")

    behind_selection, behind_gate, behind_budget = OnlyRecord(), OnlyRecord(), OnlyRecord()
    gate = TriggerGate(parse_expression("fc 3"), before=10.0, after=10.0)
    gate.add(Bare())
    gate.add(behind_gate)
    budget = FrameBudget(100, lambda: None, None, View())
    wrappers = [
        Selection([Bare(), behind_selection], View()),
        gate,
        budget,
        Limited(Bare(), budget),
        Limited(behind_budget, budget),
        Bare(),
    ]
    hub = Hub(Pipeline(), wrappers)
    hub.run_items(polling(hub, 3))
    hub.tick(2000.0)
    hub.close()
    assert not hub.failures
    frames = [
        [r for r in got.records if r.frame is not None]
        for got in (behind_selection, behind_gate, behind_budget)
    ]
    assert [len(f) for f in frames] == [6, 6, 6]
