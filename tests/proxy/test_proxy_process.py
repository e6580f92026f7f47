"""The TCP proxy forwards in a child process and observes in its parent
(:mod:`mbmon.proxy.remote`): forwarding goes on while the observing process is
stopped, a lost child ends the run with an error, the pipe between them keeps
order and meaning, and a pipe nobody reads makes the child skip observation
(counted, reported) instead of growing or blocking."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mbmon.model import Chunk, Direction, EventKind, Stream, Transport
from mbmon.proxy.remote import PipeObserver, PipeOut, decode_records
from tests.proxy.test_proxy_e2e import (
    ENV,
    adu,
    connect,
    expected_hr,
    fake,
    proxy,
    read_adu,
    read_hr,
    rpc,
)


def _children(pid: int) -> list[int]:
    out: list[int] = []
    for task in os.listdir(f"/proc/{pid}/task"):
        text = Path(f"/proc/{pid}/task/{task}/children").read_text()
        out += [int(x) for x in text.split()]
    return out


def test_forwarding_goes_on_while_the_observing_process_is_stopped(tmp_path: Path) -> None:
    with fake() as up, proxy(up.port, "--quiet", "-w", "seen.jsonl", tmp=tmp_path) as p:
        sock = connect(p.port)
        for tid in range(50):
            assert rpc(sock, tid, read_hr(tid, 2)) == expected_hr(tid, 1, tid, 2)
        os.kill(p.proc.pid, signal.SIGSTOP)  # the hub, the log, the console: frozen
        try:
            for tid in range(50, 550):  # answered all the same, by the child
                assert rpc(sock, tid, read_hr(tid, 2)) == expected_hr(tid, 1, tid, 2)
        finally:
            os.kill(p.proc.pid, signal.SIGCONT)
        sock.close()
        _out, err = p.stop()
    assert p.returncode == 0
    assert "requests 550, responses 550" in err
    assert "not observed" not in err
    lines = (tmp_path / "seen.jsonl").read_text().replace(" ", "").splitlines()
    assert sum('"kind":"request"' in line for line in lines) == 550  # observed later, all
    assert sum('"kind":"response"' in line for line in lines) == 550


@pytest.mark.parametrize("loop", ["uvloop", "asyncio"])
def test_the_forwarding_process_runs_the_loop_asked_for(tmp_path: Path, loop: str) -> None:
    """uvloop when installed (a dependency on POSIX), asyncio's loop when
    MBMON_EVENT_LOOP=asyncio; either way one ADU per segment, several in one, and
    one split in two (the fast path, the decoder, the buffer) come back whole."""
    if loop == "uvloop":
        pytest.importorskip("uvloop")
    env = {**ENV, "MBMON_EVENT_LOOP": loop}
    with (
        fake() as up,
        proxy(up.port, "--quiet", "-w", "seen.jsonl", tmp=tmp_path, env=env) as p,
    ):
        sock = connect(p.port)
        for tid in range(20):
            assert rpc(sock, tid, read_hr(tid, 3)) == expected_hr(tid, 1, tid, 3)
        (child,) = _children(p.proc.pid)
        maps = Path(f"/proc/{child}/maps").read_text()
        assert ("uvloop" in maps) == (loop == "uvloop")
        sock.sendall(b"".join(adu(tid, 1, read_hr(tid, 2)) for tid in (100, 101, 102)))
        for tid in (100, 101, 102):
            assert read_adu(sock) == expected_hr(tid, 1, tid, 2)
        whole = adu(103, 1, read_hr(7, 4))
        sock.sendall(whole[:9])
        time.sleep(0.1)
        sock.sendall(whole[9:])
        assert read_adu(sock) == expected_hr(103, 1, 7, 4)
        sock.close()
        _out, err = p.stop()
    assert p.returncode == 0
    assert "requests 24, responses 24" in err
    lines = (tmp_path / "seen.jsonl").read_text().replace(" ", "").splitlines()
    assert sum('"kind":"request"' in line for line in lines) == 24
    assert sum('"kind":"response"' in line for line in lines) == 24


def test_a_lost_forwarding_process_ends_the_run_with_an_error(tmp_path: Path) -> None:
    with fake() as up, proxy(up.port, "--quiet", tmp=tmp_path) as p:
        sock = connect(p.port)
        assert rpc(sock, 1, read_hr(0, 1)) == expected_hr(1, 1, 0, 1)
        time.sleep(0.5)  # its counters (sent ten times a second) have reached the parent
        (child,) = _children(p.proc.pid)
        os.kill(child, signal.SIGKILL)
        p.proc.wait(20)  # ends by itself: the pipe's end stops the hub
        _out, err = p.stop()
        sock.close()
    assert p.returncode == 1
    assert "forwarding process ended unexpectedly" in err
    assert "requests 1, responses 1" in err  # the last counters it sent


def test_pipe_records_round_trip_in_order() -> None:
    async def main() -> tuple[list, list]:
        loop = asyncio.get_running_loop()
        r, w = os.pipe()
        out = PipeOut(w, loop, lambda: None)
        a = Stream(7, Transport.TCP, "127.0.0.1:5000", "127.0.0.1:502")
        out.send(("stream", 7, "tcp", a.client, a.server))
        observer = PipeObserver(out, lambda *x: a, max_backlog=50_000)
        observer.bind(loop.call_soon)
        observer.event(a, EventKind.CONNECT, {}, 1.0)
        observer.chunk(a, Direction.C2S, b"\x00\x01\x00\x00\x00\x06\x01\x03\x00\x00\x00\x01", 2.0)
        observer.chunk(a, Direction.S2C, b"\x00\x01\x00\x00\x00\x05\x01\x03\x02\x00\x2a", 3.5)
        observer.event(None, EventKind.NOTICE, {"message": "hello", "tid": 1}, 4.0)
        out.send(("stats", {"requests": 1}, {"clients": 1}, True))
        await asyncio.sleep(0)
        out.finish()
        data = b""
        while part := os.read(r, 65536):
            data += part
        os.close(r)
        made: list[Stream] = []

        def new_stream(transport: Transport, client: str, server: str) -> Stream:
            made.append(Stream(100 + len(made), transport, client, server))
            return made[-1]

        items, others, used = decode_records(bytearray(data), {}, new_stream)
        assert used == len(data)
        return items, others

    items, others = asyncio.run(main())
    hub_stream = Stream(100, Transport.TCP, "127.0.0.1:5000", "127.0.0.1:502")
    assert [type(i).__name__ for i in items] == ["Event", "Chunk", "Chunk", "Event"]
    assert items[0].stream == hub_stream and items[0].kind is EventKind.CONNECT
    request = bytes.fromhex("000100000006010300000001")
    answer = bytes.fromhex("000100000005010302002A")
    assert items[1] == Chunk(2.0, hub_stream, Direction.C2S, request)
    assert items[2] == Chunk(3.5, hub_stream, Direction.S2C, answer)
    assert items[3].stream is None and dict(items[3].info) == {"message": "hello", "tid": 1}
    assert others == [("stats", {"requests": 1}, {"clients": 1}, True)]


def test_an_unread_pipe_bounds_the_backlog_and_reports_what_was_skipped() -> None:
    async def main() -> tuple[int, int, int, list]:
        loop = asyncio.get_running_loop()
        r, w = os.pipe()
        out = PipeOut(w, loop, lambda: None)
        stream = Stream(0, Transport.TCP, "c:1", "s:2")
        out.send(("stream", 0, "tcp", "c:1", "s:2"))
        observer = PipeObserver(out, lambda *x: stream, max_backlog=1000)
        observer.bind(loop.call_soon)
        payload = bytes(200)
        for i in range(20_000):  # nobody reads: the pipe fills, then the buffer
            observer.chunk(stream, Direction.C2S, payload, float(i))
            if i % 100 == 0:
                await asyncio.sleep(0)
        await asyncio.sleep(0)
        skipped, buffered = observer.skipped, len(out.buf)
        # the reader comes back: everything that was kept arrives, then the notice
        data = bytearray()
        os.set_blocking(r, False)

        async def read_all() -> None:
            while True:
                try:
                    part = os.read(r, 1 << 20)
                except BlockingIOError:
                    if not out.buf:
                        return
                    await asyncio.sleep(0.001)
                    continue
                data.extend(part)

        await read_all()
        observer.chunk(stream, Direction.C2S, payload, 99999.0)
        await asyncio.sleep(0)
        out.finish()
        os.set_blocking(r, True)
        while part := os.read(r, 1 << 20):
            data.extend(part)
        os.close(r)
        items, _others, _used = decode_records(data, {}, lambda *x: stream)
        return skipped, buffered, len(items), items[-2:]

    skipped, buffered, n, last = asyncio.run(main())
    assert skipped > 0
    assert buffered <= 1100 * 216  # the child's buffer: about max_backlog items, no more
    assert n == 20_000 - skipped + 2  # what was kept, the notice, the last chunk
    assert last[0].kind is EventKind.NOTICE
    assert f"{skipped} chunks were forwarded but not observed" in last[0].info["message"]
    assert last[1].ts == 99999.0


def _policies(pid: int) -> list[int]:
    return [os.sched_getscheduler(int(tid)) for tid in os.listdir(f"/proc/{pid}/task")]


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux's")
@pytest.mark.parametrize("asked", ["", "normal"])
def test_the_observing_process_runs_idle_and_the_forwarding_at_its_own_priority(
    tmp_path: Path, asked: str
) -> None:
    """``mbmon proxy -w x.mcap``: every thread of the observing process (the hub and the
    compiled core, the pipe's reader, the log's writer) runs SCHED_IDLE, so it never
    takes a core from the forwarding chain; the forwarding process keeps the policy it
    was started with. ``MBMON_OBSERVE_PRIORITY=normal`` keeps the observer there too."""
    env = {**ENV, "MBMON_OBSERVE_PRIORITY": asked}
    with (
        fake() as up,
        proxy(up.port, "--quiet", "-w", "seen.mcap", tmp=tmp_path, env=env) as p,
    ):
        sock = connect(p.port)
        for tid in range(20):
            assert rpc(sock, tid, read_hr(tid, 2)) == expected_hr(tid, 1, tid, 2)
        observing = _policies(p.proc.pid)
        (child,) = _children(p.proc.pid)
        forwarding = _policies(child)
        sock.close()
        _out, err = p.stop()
    assert p.returncode == 0, err
    assert len(observing) >= 3  # the main thread, the pipe's reader, the log's writer
    assert set(observing) == {os.SCHED_OTHER if asked else os.SCHED_IDLE}
    assert set(forwarding) == {os.SCHED_OTHER}
    assert "requests 20, responses 20" in err


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux's")
def test_an_observer_starved_by_busy_cores_catches_up_and_loses_nothing(tmp_path: Path) -> None:
    """With every core kept busy at normal priority, the idle observer gets next to no
    CPU: the forwarding goes on, its observations wait (within the backlog), and once
    the cores are free again the log holds every request and answer."""
    from tests.proxy.test_proxy_own_answers import mcap_json

    hogs: list[subprocess.Popen[bytes]] = []
    with fake() as up, proxy(up.port, "--quiet", "-w", "seen.mcap", tmp=tmp_path) as p:
        sock = connect(p.port)
        assert rpc(sock, 0, read_hr(0, 2)) == expected_hr(0, 1, 0, 2)
        busy = "import time\nend = time.monotonic() + 20\nwhile time.monotonic() < end: pass"
        try:
            hogs = [
                subprocess.Popen([sys.executable, "-c", busy]) for _ in range(os.cpu_count() or 2)
            ]
            for tid in range(1, 1500):  # answered all the same, by the child
                assert rpc(sock, tid, read_hr(tid, 2)) == expected_hr(tid, 1, tid, 2)
        finally:
            for hog in hogs:
                hog.kill()
                hog.wait()
        sock.close()
        _out, err = p.stop()
    assert p.returncode == 0, err
    assert "requests 1500, responses 1500" in err
    assert "not observed" not in err
    frames = mcap_json(tmp_path / "seen.mcap", "/modbus/frames")
    assert sum(f.get("kind") == "request" for f in frames) == 1500
    assert sum(f.get("kind") == "response" for f in frames) == 1500


def _messages(path: Path, topic: str) -> int:
    """How many messages ``topic`` has in the MCAP log at ``path`` (its summary's count,
    read with the ``mcap`` package's reader)."""
    from mcap.reader import make_reader

    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    ids = [c.id for c in summary.channels.values() if c.topic == topic]
    return sum(summary.statistics.channel_message_counts.get(i, 0) for i in ids)


def _may_leave_idle() -> bool:
    import resource

    return os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_NICE)[0] >= 20


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux's")
@pytest.mark.skipif(not _may_leave_idle(), reason="leaving SCHED_IDLE needs root or RLIMIT_NICE")
def test_a_starved_observer_catches_up_at_normal_priority_then_yields_again(
    tmp_path: Path,
) -> None:
    """With every core kept busy, the idle observer falls behind; a large read of the
    pipe puts its threads back to normal priority (it catches up instead of skipping);
    once its reads are small again for a while, they go back to idle."""
    hogs: list[subprocess.Popen[bytes]] = []
    busy = "import time\nend = time.monotonic() + 30\nwhile time.monotonic() < end: pass"
    seen: list[set[int]] = []
    tid = 0
    with fake() as up, proxy(up.port, "--quiet", "-w", "seen.mcap", tmp=tmp_path) as p:
        sock = connect(p.port)
        try:
            hogs = [
                subprocess.Popen([sys.executable, "-c", busy]) for _ in range(os.cpu_count() or 2)
            ]
            end = time.monotonic() + 25
            while time.monotonic() < end and (not seen or seen[-1] != {os.SCHED_OTHER}):
                # 100 requests at once, large answers (125 registers): the pipe fills fast
                tids = [(tid + k) & 0xFFFF for k in range(1, 101)]
                tid += 100
                sock.sendall(b"".join(adu(t, 1, read_hr(1, 125)) for t in tids))
                for t in tids:
                    assert read_adu(sock) == expected_hr(t, 1, 1, 125)
                seen.append(set(_policies(p.proc.pid)))
        finally:
            for hog in hogs:
                hog.kill()
                hog.wait()
        assert seen[-1] == {os.SCHED_OTHER}, seen  # behind: back at normal priority
        end = time.monotonic() + 20
        while time.monotonic() < end and seen[-1] != {os.SCHED_IDLE}:
            for _ in range(20):  # light traffic: one small read a handover
                tid += 1
                assert rpc(sock, tid & 0xFFFF, read_hr(1, 2)) == expected_hr(tid & 0xFFFF, 1, 1, 2)
            time.sleep(0.02)
            seen.append(set(_policies(p.proc.pid)))
        assert seen[-1] == {os.SCHED_IDLE}, seen  # caught up: idle again
        sock.close()
        _out, err = p.stop()
    assert p.returncode == 0, err
    assert f"requests {tid}, responses {tid}" in err
    assert "not observed" not in err
    assert _messages(tmp_path / "seen.mcap", "/modbus/frames") == 2 * tid  # every ADU
