"""The proxy engine in a process of its own: forwarding never waits for observation.

In one process the engine (asyncio, forwarding) and the hub (decode, pairing,
records, logs) share one GIL: every request the hub observes is CPU the
forwarding cannot have at that moment, and at one client the hub's wake-ups
alone added tens of microseconds to each round trip (docs/performance.md,
"Proxy"). Here the same :class:`~mbmon.proxy.engine.ProxyEngine` runs in a
child process, and its observations (the very chunks and events it hands to the
hub in one process) come to the parent's hub through a pipe:

* child: :class:`PipeObserver` encodes each chunk and event as the engine makes
  it into :class:`PipeOut`'s buffer (chunks as a 16-byte header and their bytes,
  other records pickled; no objects in between), and the engine's handover
  commits the batch: :class:`PipeOut` writes it to the pipe without ever
  blocking: a full pipe waits in the buffer, written when the loop sees the
  pipe writable. It is the :class:`~mbmon.proxy.observer.Observer`'s backlog
  meter: what is still in the buffer counts as not yet seen, so past
  ``max_backlog`` items chunks are forwarded but not observed (counted and
  reported), exactly as in one process.
* parent: :class:`ProxyProcess` (the interface of
  :class:`~mbmon.proxy.runner.ProxyThread`) starts the child, reads the pipe in
  a thread, rebuilds the chunks and events (streams get the hub's own ids from
  ``hub.new_stream``) and hands them to ``hub.submit``. While the hub is more
  than ``max_backlog`` items behind it stops reading, so the pipe and then the
  child's buffer fill, and the child skips: memory stays bounded at every step.
  :class:`RemoteEngine` is what the command sees of the engine: its counters
  and live figures, sent by the child ten times a second and at the end.

Once the child has started, the parent runs at idle CPU priority
(:func:`~mbmon.proxy.priority.observe_idle`, when :attr:`ProxyConfig.observe_idle`
asks): the forwarding chain never waits for the observer's bursts; far behind, or
stopping, it is back at normal priority where the system allows
(:class:`~mbmon.proxy.priority.Catchup`).

Stopping: the parent writes to (or closes) a control pipe; the child stops the
engine (its last events, the disconnects, still come), sends its final counters
and closes the data pipe, whose end of file stops the hub. The child ignores
Ctrl-C and SIGTERM (the terminal sends Ctrl-C to both; the parent decides); if
the parent dies, the control pipe's end of file stops it. It stays in the
parent's session: Linux's autogroup scheduler would otherwise give it a CPU
share of its own against its parent, which halved the throughput on a busy
machine (docs/performance.md).

Only the TCP proxy runs this way; the serial variants (one request at a time on
a bus) and ``mbmon demo`` keep the engine in a thread (``attach_engine``).
"""

from __future__ import annotations

import asyncio
import itertools
import os
import pickle
import signal
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport, fast_constructor
from mbmon.proxy.config import ProxyConfig, ProxyStats
from mbmon.proxy.engine import ProxyEngine
from mbmon.proxy.observer import Observer
from mbmon.proxy.priority import Catchup, observe_idle

__all__ = [
    "CHUNK_HEAD",
    "PipeObserver",
    "PipeOut",
    "ProxyProcess",
    "RemoteEngine",
    "child_main",
    "decode_records",
]

#: The head of a chunk record in the observation pipe: tag, stream id, timestamp,
#: direction, length; the chunk's bytes follow (``CHUNK_HEAD.size`` bytes a chunk
#: on top of its own, what a benchmark needs to size the pipe's backlog).
CHUNK_HEAD = struct.Struct("<cIdBH")
#: other records: tag, length; then a pickle
_OBJECT = struct.Struct("<cI")
_C = b"C"
_O = b"O"
_DIRECTIONS = list(Direction)
_DIRECTION_CODE = {d: i for i, d in enumerate(_DIRECTIONS)}
_new_chunk = fast_constructor(Chunk)
_pack_head = CHUNK_HEAD.pack

#: How much the kernel may hold in the pipe (Linux: F_SETPIPE_SZ; default 64 KiB).
PIPE_SIZE = 1 << 20
#: How often the child sends its counters (the live monitor's figures).
STATS_PERIOD = 0.1
#: The environment variable that picks the forwarding process's event loop:
#: ``asyncio`` for asyncio's own; anything else, uvloop when installed.
EVENT_LOOP_ENV = "MBMON_EVENT_LOOP"
#: How long the parent waits for the child to listen (imports, binding).
START_TIMEOUT = 30.0


class PipeOut:
    """The child's end of the observation pipe: encodes batches, never blocks.

    ``seen`` counts the items written to the pipe whole (the Observer's meter:
    ``sent - seen`` is what waits in :attr:`buf`).
    """

    def __init__(self, fd: int, loop: asyncio.AbstractEventLoop, on_broken: Callable[[], None]):
        self.fd = fd
        self.loop = loop
        self.on_broken = on_broken
        os.set_blocking(fd, False)
        try:
            import fcntl

            fcntl.fcntl(fd, 1031, PIPE_SIZE)  # F_SETPIPE_SZ (Linux)
        except (ImportError, OSError):
            pass
        self.buf = bytearray()
        self.written = 0  # bytes ever written to the pipe
        self.items = 0  # items ever put in buf
        self.seen = 0  # items ever written whole
        self._marks: deque[tuple[int, int]] = deque()  # (bytes end, items) per batch
        self._watching = False
        self.broken = False

    def put_chunk(self, stream_id: int, direction: Direction, data: bytes, ts: float) -> None:
        """Encode one chunk into the buffer (written at the next :meth:`commit`)."""
        buf = self.buf
        buf += CHUNK_HEAD.pack(_C, stream_id, ts, _DIRECTION_CODE[direction], len(data))
        buf += data
        self.items += 1

    def put_event(self, event: Event) -> None:
        """Encode one event into the buffer (written at the next :meth:`commit`)."""
        sid = -1 if event.stream is None else event.stream.id
        self._object(("event", event.ts, sid, str(event.kind), dict(event.info)))
        self.items += 1

    def commit(self) -> None:
        """What the buffer holds is a batch: write what the pipe takes now."""
        self._marks.append((self.written + len(self.buf), self.items))
        self.drain()

    def send(self, record: tuple[Any, ...]) -> None:
        """A record that is not an item (a stream, counters, ready, error): now."""
        self._object(record)
        self.drain()

    def _object(self, record: tuple[Any, ...]) -> None:
        data = pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL)
        self.buf += _OBJECT.pack(_O, len(data))
        self.buf += data

    def drain(self) -> None:
        """Write what the pipe takes now; wait for it to be writable for the rest."""
        buf = self.buf
        while buf and not self.broken:
            try:
                n = os.write(self.fd, buf)
            except BlockingIOError:
                break
            except OSError:  # the parent is gone
                self.broken = True
                buf.clear()
                self.on_broken()
                break
            del buf[:n]
            self.written += n
        marks = self._marks
        while marks and marks[0][0] <= self.written:
            self.seen = marks.popleft()[1]
        if buf and not self.broken:
            if not self._watching:
                self.loop.add_writer(self.fd, self.drain)
                self._watching = True
        elif self._watching:
            self.loop.remove_writer(self.fd)
            self._watching = False

    def finish(self) -> None:
        """Write everything left (blocking: the loop has ended) and close the pipe."""
        if self._watching:
            self.loop.remove_writer(self.fd)
            self._watching = False
        if not self.broken and self.buf:
            os.set_blocking(self.fd, True)
            try:
                view = memoryview(self.buf)
                while view:
                    n = os.write(self.fd, view)
                    view = view[n:]
                view.release()
            except OSError:
                pass
        self.buf.clear()
        os.close(self.fd)


class PipeObserver(Observer):
    """The child's observer: each chunk and event is encoded into the pipe's buffer
    as it comes (no :class:`~mbmon.model.Chunk` object, no batch list: two a
    request), and the engine's handover (a ``call_later`` of
    :attr:`~mbmon.proxy.config.ProxyConfig.handover`) commits what waits there to
    the pipe. The backlog rule is :class:`~mbmon.proxy.observer.Observer`'s."""

    def __init__(
        self,
        out: PipeOut,
        new_stream: Callable[[Transport, str, str], Stream],
        *,
        max_backlog: int,
    ) -> None:
        super().__init__(
            self._emit,  # never called by the base: this observer emits everything itself
            new_stream,
            meter=out,  # type: ignore[arg-type]
            max_backlog=max_backlog,
        )
        self._out = out
        self._due = False

    def chunk(self, stream: Stream, direction: Direction, data: bytes, ts: float) -> None:
        # two a request, in the forwarding process: the common case (the pipe keeps
        # up) inline, the backlog rule (Observer._admit) and the handover as calls
        out = self._out
        if self._skipping or self.sent - out.seen > self._max_backlog:
            if not self._admit(ts):
                return
        else:
            self.sent += 1
        buf = out.buf
        buf += _pack_head(_C, stream.id, ts, _DIRECTION_CODE[direction], len(data))
        buf += data
        out.items += 1
        if not self._due:
            self._handover()

    def _emit(self, item: Chunk | Event) -> None:  # events: chunks never come here
        self._out.put_event(item)  # type: ignore[arg-type]
        self._handover()

    def _handover(self) -> None:
        if self._due:
            return
        call_soon = self._call_soon
        if call_soon is None:  # not bound to a loop yet: at once
            self._out.commit()
            return
        self._due = True
        call_soon(self.flush)

    def flush(self) -> None:
        """Commit what waits in the pipe's buffer (the engine's handover)."""
        self._due = False
        self._out.commit()


def decode_records(
    buf: bytearray, streams: dict[int, Stream], new_stream: Callable[..., Stream]
) -> tuple[list[Chunk | Event], list[tuple[Any, ...]], int]:
    """Parse the whole records at the start of ``buf``: the chunks and events (in
    order), the other records, and how many bytes were used. ``streams`` maps the
    child's stream ids to the hub's streams; ``new_stream(transport, client,
    server)`` makes them."""
    items: list[Chunk | Event] = []
    others: list[tuple[Any, ...]] = []
    pos = 0
    n = len(buf)
    unpack = CHUNK_HEAD.unpack_from
    head = CHUNK_HEAD.size
    ohead = _OBJECT.size
    directions = _DIRECTIONS
    while n - pos >= 5:
        tag = buf[pos]
        if tag == 0x43:  # C
            if n - pos < head:
                break
            _tag, sid, ts, d, length = unpack(buf, pos)
            end = pos + head + length
            if end > n:
                break
            items.append(_new_chunk(ts, streams[sid], directions[d], bytes(buf[pos + head : end])))
            pos = end
            continue
        _tag, length = _OBJECT.unpack_from(buf, pos)
        end = pos + ohead + length
        if end > n:
            break
        record = pickle.loads(buf[pos + ohead : end])
        pos = end
        what = record[0]
        if what == "stream":
            _, sid, transport, client, server = record
            streams[sid] = new_stream(Transport(transport), client, server)
        elif what == "event":
            _, ts, sid, kind, info = record
            if "answers_on" in info:  # a stream id of the child's: the hub's instead
                info = {**info, "answers_on": streams[info["answers_on"]].id}
            items.append(Event(ts, None if sid < 0 else streams[sid], EventKind(kind), info))
        else:
            others.append(record)
    return items, others, pos


# ----------------------------------------------------------------------------- child


def child_main(data_fd: int, ctrl_fd: int) -> None:
    """The child process: read the config from the control pipe, run the engine,
    observations to the data pipe, until the parent says stop (or is gone)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when to stop
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    head = _read_exactly(ctrl_fd, 4)
    config: ProxyConfig = pickle.loads(_read_exactly(ctrl_fd, struct.unpack("<I", head)[0]))
    run_loop(_child(config, data_fd, ctrl_fd))


def run_loop(main: Any) -> None:
    """Run the forwarding loop's coroutine ``main`` on uvloop when it is installed
    (a dependency on POSIX: its loop and transports are C, which takes about a third
    off the forwarding process's CPU per request, docs/performance.md), else on
    asyncio's own loop. ``MBMON_EVENT_LOOP=asyncio`` asks for asyncio's loop."""
    if os.environ.get(EVENT_LOOP_ENV, "").strip().lower() != "asyncio":
        try:
            import uvloop
        except ImportError:
            pass
        else:
            uvloop.run(main)
            return
    asyncio.run(main)


def _read_exactly(fd: int, n: int) -> bytes:
    out = b""
    while len(out) < n:
        part = os.read(fd, n - len(out))
        if not part:
            raise SystemExit(0)  # the parent is gone before it said anything
        out += part
    return out


async def _child(config: ProxyConfig, data_fd: int, ctrl_fd: int) -> None:
    loop = asyncio.get_running_loop()
    engine: ProxyEngine | None = None

    def stop() -> None:
        if engine is not None:
            engine.request_stop()

    out = PipeOut(data_fd, loop, stop)
    ids = itertools.count()

    def new_stream(transport: Transport, client: str, server: str) -> Stream:
        stream = Stream(next(ids), transport, client, server)
        out.send(("stream", stream.id, str(transport), client, server))
        return stream

    observer = PipeObserver(out, new_stream, max_backlog=config.max_backlog)
    # the engine binds the observer to its handover timer (its items are in the
    # pipe's buffer already; each handover commits them): no submit of its own
    engine = ProxyEngine(config, observer)
    try:
        address = await engine.start()
    except OSError as exc:
        out.send(("error", exc.errno, exc.strerror, str(exc)))
        out.finish()
        return
    out.send(("ready", address[0], address[1]))

    def on_ctrl() -> None:
        try:
            data = os.read(ctrl_fd, 64)
        except OSError:
            data = b""
        if not data or b"s" in data:
            loop.remove_reader(ctrl_fd)
            stop()

    os.set_blocking(ctrl_fd, False)
    loop.add_reader(ctrl_fd, on_ctrl)

    def counters(final: bool = False) -> tuple[Any, ...]:
        stats = engine.stats.as_dict()
        stats["not_observed"] = observer.skipped
        return ("stats", stats, engine.figures(), final)

    async def report() -> None:
        while True:
            await asyncio.sleep(STATS_PERIOD)
            out.send(counters())

    reporter = loop.create_task(report())
    try:
        await engine.serve()
    finally:
        reporter.cancel()
        observer.flush()
        out.send(counters(final=True))
        out.finish()


# ----------------------------------------------------------------------------- parent


class RemoteEngine:
    """What the command sees of an engine in a child process: the last counters and
    figures it sent (read from any thread)."""

    def __init__(self) -> None:
        self.stats = ProxyStats()
        self.address: tuple[str, int] | None = None
        self._figures: dict[str, Any] = {"clients": 0, "upstream": "not connected yet"}
        self.final = False  # the child sent its last counters (it ended in order)

    def figures(self) -> dict[str, Any]:
        """The proxy's own figures for the live monitor's header."""
        return dict(self._figures)

    def update(self, stats: dict[str, int], figures: dict[str, Any], final: bool) -> None:
        self.stats = ProxyStats(**stats)
        self._figures = figures
        self.final = self.final or final


class ProxyProcess:
    """Runs a :class:`~mbmon.proxy.engine.ProxyEngine` in a child process; the same
    calls as :class:`~mbmon.proxy.runner.ProxyThread` (``start``, ``stop``,
    ``join``, ``engine``). ``hub`` gets the observations (``submit``,
    ``new_stream``) and bounds their backlog (``hub.seen``: what it has taken);
    ``on_exit`` runs when the child's pipe has ended."""

    def __init__(
        self,
        config: ProxyConfig,
        hub: Any,
        on_exit: Callable[[], None] | None = None,
        stage: Any = None,
    ) -> None:
        self.config = config
        self.hub = hub
        #: the compiled core's stage (:class:`mbmon.core.chunks.ChunkCore`): the pipe's
        #: reads go to its ``take`` instead of becoming chunks and events here
        self.stage = stage
        self.engine = RemoteEngine()
        self._on_exit = on_exit
        self._proc: subprocess.Popen[bytes] | None = None
        self._ctrl: int | None = None
        self._data: int | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stopping = False
        self._reader = threading.Thread(target=self._read, name="mbmon-proxy-pipe", daemon=True)
        self.submitted = 0
        #: what :func:`observe_idle` set for this (the observing) process, if asked
        self.priority: str | None = None
        #: back at normal priority while far behind (with an idle observer)
        self.catchup: Catchup | None = None
        self._last_read = 0

    @property
    def skipped(self) -> int:
        """Chunks the child forwarded but could not hand over (the observer was behind)."""
        return self.engine.stats.not_observed

    @property
    def returncode(self) -> int | None:
        return None if self._proc is None else self._proc.poll()

    def start(self) -> tuple[str, int]:
        """Start the child; the address it listens on, or the ``OSError`` it met."""
        data_r, data_w = os.pipe()
        ctrl_r, ctrl_w = os.pipe()
        package_root = str(Path(__file__).resolve().parents[2])  # this very mbmon
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(
            p for p in (package_root, env.get("PYTHONPATH", "")) if p
        )
        code = (
            "import sys; from mbmon.proxy.remote import child_main; "
            "child_main(int(sys.argv[1]), int(sys.argv[2]))"
        )
        # the child starts with Ctrl-C ignored (inherited through exec, and Python
        # keeps it so), not only once child_main has run: the terminal sends Ctrl-C
        # to both processes, and the parent is the one that decides
        main = threading.current_thread() is threading.main_thread()
        old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-c", code, str(data_w), str(ctrl_r)],
                pass_fds=(data_w, ctrl_r),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                env=env,
            )
        finally:
            if old is not None:
                signal.signal(signal.SIGINT, old)
            os.close(data_w)
            os.close(ctrl_r)
        self._data, self._ctrl = data_r, ctrl_w
        if self.config.observe_idle:  # the child runs at the priority it was started with
            self.priority = observe_idle()
            if self.priority == "idle":
                self.catchup = Catchup(self.config.max_backlog, PIPE_SIZE)
        blob = pickle.dumps(self.config, protocol=pickle.HIGHEST_PROTOCOL)
        os.write(ctrl_w, struct.pack("<I", len(blob)) + blob)
        self._reader.start()
        if not self._ready.wait(START_TIMEOUT):
            self._kill()
            raise OSError("the proxy's forwarding process did not start")
        if self._error is not None:
            raise self._error
        assert self.engine.address is not None
        return self.engine.address

    def _read(self) -> None:
        """The reader thread: pipe -> chunks and events -> ``hub.submit``."""
        fd = self._data
        assert fd is not None
        hub = self.hub
        limit = self.config.max_backlog
        streams: dict[int, Stream] = {}
        buf = bytearray()
        # one buffer for every read: os.read would make (mmap, then unmap) a new
        # 1 MiB bytes object per read
        space = memoryview(bytearray(PIPE_SIZE))
        try:
            while True:
                n = os.readv(fd, [space])
                if not n:
                    break
                self._last_read = n
                buf += space[:n]
                if self.stage is not None:
                    self._to_core(buf)
                    continue
                items, others, used = decode_records(buf, streams, hub.new_stream)
                del buf[:used]
                for record in others:
                    self._record(record)
                if items:
                    self.submitted += len(items)
                    hub.submit(lambda items=items: items)
                    # the hub is behind: read no more, so the pipe and then the
                    # child's buffer fill and the child skips (bounded memory)
                    self._pace(self.submitted - hub.seen)
                    while self.submitted - hub.seen > limit and not self._stopping:
                        time.sleep(0.005)
        except OSError:
            pass
        finally:
            os.close(fd)
            if not self._ready.is_set():
                self._error = OSError("the proxy's forwarding process ended before listening")
                self._ready.set()
            if self._proc is not None:
                try:
                    self._proc.wait(5)
                except subprocess.TimeoutExpired:
                    self._kill()
            if self._on_exit is not None:
                self._on_exit()

    def _to_core(self, buf: bytearray) -> None:
        """The whole records at the start of ``buf`` (taken out of it) to the core's
        stage in the hub's thread: runs of chunk records as they are (bytes), the
        streams (with the hub's ids) and events between them; the other records
        (counters, ready, error) are this thread's. Waits while the hub is behind."""
        stage = self.stage
        hub = self.hub
        used, chunks, objects = stage.scan(buf, len(buf))
        if not used:
            return
        segments: list[Any] = []
        pos = 0
        events = 0
        for start, end in objects:
            if start - _OBJECT.size > pos:
                segments.append(bytes(buf[pos : start - _OBJECT.size]))
            record = pickle.loads(buf[start:end])
            what = record[0]
            if what == "stream":
                _, sid, transport, client, server = record
                segments.append(
                    ("stream", sid, hub.new_stream(Transport(transport), client, server))
                )
            elif what == "event":
                segments.append(record)
                events += 1
            else:
                self._record(record)
            pos = end
        if used > pos:
            segments.append(bytes(buf[pos:used]))
        del buf[:used]
        if not segments:
            return
        self.submitted += chunks + events
        take = stage.take
        hub.submit(lambda: take(segments))
        limit = self.config.max_backlog
        # the hub is behind: read no more, so the pipe and then the child's buffer
        # fill and the child skips (bounded memory)
        self._pace(self.submitted - (hub.seen + stage.taken))
        while self.submitted - (hub.seen + stage.taken) > limit and not self._stopping:
            time.sleep(0.005)

    def _pace(self, backlog: int) -> None:
        """After a read handed over: an idle observer far behind goes back to normal
        priority while it catches up (:class:`Catchup`)."""
        if self.catchup is not None:
            self.catchup.read(self._last_read, backlog)

    def _record(self, record: tuple[Any, ...]) -> None:
        what = record[0]
        if what == "stats":
            self.engine.update(record[1], record[2], record[3])
        elif what == "ready":
            self.engine.address = (record[1], record[2])
            self._ready.set()
        elif what == "error":
            _, errno, strerror, text = record
            self._error = OSError(errno, strerror) if errno is not None else OSError(text)
            self._ready.set()

    def stop(self) -> None:
        """Ask the child to stop (safe from any thread and from signal handlers)."""
        self._stopping = True
        if self.catchup is not None:
            self.catchup.stop()
        ctrl = self._ctrl
        if ctrl is not None:
            try:
                os.write(ctrl, b"s")
            except OSError:
                pass

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the child and the pipe's end; whether both have ended."""
        if self._reader.is_alive():
            self._reader.join(timeout)
        ended = not self._reader.is_alive()
        if ended and self._ctrl is not None:
            try:
                os.close(self._ctrl)
            except OSError:
                pass
            self._ctrl = None
        return ended

    def _kill(self) -> None:
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
