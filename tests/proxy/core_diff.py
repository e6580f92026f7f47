"""The proxy's differential harness: the same bytes of the observation pipe (what the
forwarding child sends its parent), cut into the same reads, with the same ticks,
through the parent's reference wiring (``decode_records`` → hub → pipeline →
console) and through the compiled core's stage (``ProxyProcess._to_core`` →
:class:`mbmon.core.chunks.ChunkCore` → lines, the pipeline behind it after a
hand-over), both in this process; and a recorder that keeps a real proxy's pipe
bytes (a real child process between real sockets) for them."""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any

from mbmon.format import View
from mbmon.hub import Hub
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.proxy.config import ProxyConfig
from mbmon.proxy.remote import _OBJECT, CHUNK_HEAD, ProxyProcess, decode_records
from mbmon.sinks.base import SinkContext
from mbmon.sinks.console import ConsoleListener
from mbmon.sinks.mcap import McapSink

#: the pipe's direction codes
C2S, S2C = 0, 1


# --------------------------------------------------------------------------- making pipe bytes


def chunk(sid: int, d: int, ts: float, data: bytes) -> bytes:
    """A chunk record of the pipe."""
    return CHUNK_HEAD.pack(b"C", sid, ts, d, len(data)) + data


def obj(record: tuple[Any, ...]) -> bytes:
    """Another record of the pipe (stream, event, counters)."""
    blob = pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL)
    return _OBJECT.pack(b"O", len(blob)) + blob


def stream(sid: int, client: str, server: str) -> bytes:
    return obj(("stream", sid, "tcp", client, server))


def event(ts: float, sid: int, kind: str, info: dict[str, Any] | None = None) -> bytes:
    return obj(("event", ts, sid, kind, dict(info or {})))


def client(sid: int, ts: float, port: int, upstream: str = "127.0.0.1:502") -> bytes:
    """A client's two streams (its own and the proxy's answers to it) and its CONNECT."""
    peer = f"127.0.0.1:{port}"
    return (
        stream(sid, peer, upstream)
        + stream(sid + 1, peer, "proxy 127.0.0.1:1502")
        + event(ts, sid, "connect", {"answers_on": sid + 1, "note": "made by the proxy"})
    )


# --------------------------------------------------------------------------- the two wirings

#: a read of the pipe (its bytes) or a float: the hub ticks at that time
Step = bytes | float


def _wire(
    as_json: bool | None,
    timeout: float,
    upstream: str,
    log: Path | None,
    hub_class: type[Hub] = Hub,
) -> tuple[Hub, io.BytesIO, io.TextIOWrapper, View, Any]:
    """A hub as ``mbmon proxy`` wires it: the ``log`` first (an MCAP sink, or none),
    then a console over bytes (none when ``as_json`` is None: ``-q``; the text wrapper
    must outlive the run: collected, it would close the bytes)."""
    raw = io.BytesIO()
    out = io.TextIOWrapper(raw, encoding="utf-8", errors="backslashreplace", write_through=True)
    view = View(robot=upstream)
    hub = hub_class(Pipeline(None, PipelineConfig(timeout=timeout)), clock=lambda: 0.0)
    sink = None
    if log is not None:
        ctx = SinkContext(
            view=view,
            command_line=["mbmon", "proxy", "-w", "x.mcap"],
            source=f"proxy -> {upstream}",
            profiles=[],
            profile_specs=[],
            timeout=timeout,
            baud=None,
        )
        sink = McapSink(log, ctx)
        hub.add_listener(sink)
    if as_json is not None:
        hub.add_listener(ConsoleListener(out, view, as_json=as_json, live=True))
    return hub, raw, out, view, sink


def reference(
    steps: list[Step],
    *,
    as_json: bool | None,
    timeout: float = 4.0,
    upstream: str = "127.0.0.1:502",
    log: Path | None = None,
) -> bytes:
    """What the parent's reference wiring prints for ``steps`` (and writes to ``log``)."""
    hub, raw, out, _view, _sink = _wire(as_json, timeout, upstream, log)
    streams: dict[int, Any] = {}
    buf = bytearray()
    for step in steps:
        if isinstance(step, float):
            hub.tick(step)
            continue
        buf += step
        items, _others, used = decode_records(buf, streams, hub.new_stream)
        del buf[:used]
        hub.feed_items(items)
    hub.finish()
    hub.close()
    out.flush()
    return raw.getvalue()


class _Now(Hub):
    """A hub whose ``submit`` runs the producer at once (the harness has no loop)."""

    def submit(self, producer: Any) -> None:
        produced = producer()
        if produced:
            self.feed_items(produced)


def core(
    steps: list[Step],
    *,
    as_json: bool | None,
    timeout: float = 4.0,
    upstream: str = "127.0.0.1:502",
    log: Path | None = None,
) -> tuple[bytes, str | None]:
    """What the core's stage prints for ``steps`` (and writes to ``log``), and why it
    handed over (or None)."""
    from mbmon.core.chunks import ChunkCore

    hub, raw, out, view, sink = _wire(as_json, timeout, upstream, log, _Now)
    stage = ChunkCore(
        timeout=timeout,
        view=view,
        as_json=bool(as_json),
        write=None if as_json is None else raw.write,
        pipeline=hub.pipeline,
    )
    if sink is not None:
        stage.log_to(sink)
    hub.add_ticker(stage)
    proc = ProxyProcess(ProxyConfig("127.0.0.1", 502), hub, stage=stage)
    buf = bytearray()
    for step in steps:
        if isinstance(step, float):
            hub.tick(step)
            continue
        buf += step
        proc._to_core(buf)
    hub.finish()
    hub.close()
    out.flush()
    return raw.getvalue(), stage.handed


# --------------------------------------------------------------------------- a real proxy's pipe


class Recorder:
    """A stage that keeps the pipe's bytes as the parent reads them (nothing observed)."""

    def __init__(self) -> None:
        from mbmon.core._reader import pipe_scan

        self._scan = pipe_scan
        self.reads: list[bytes] = []
        self.taken = 1 << 60  # never behind

    def scan(self, buf: Any, n: int) -> Any:
        used, chunks, objects = self._scan(buf, n)
        if used:
            self.reads.append(bytes(buf[:used]))
        return used, chunks, objects

    def take(self, segments: list[Any]) -> list[Any]:
        return []


class Recording:
    """A real proxy (its forwarding child, listening on 127.0.0.1) whose pipe is kept:
    ``with Recording(upstream_port) as rec: ... rec.port ...``, then ``rec.reads``."""

    def __init__(self, upstream_port: int, **config: Any) -> None:
        self.hub = Hub(Pipeline(None, PipelineConfig()))
        self.recorder = Recorder()
        cfg = ProxyConfig("127.0.0.1", upstream_port, listen_port=0, **config)
        self.proc = ProxyProcess(cfg, self.hub, stage=self.recorder)
        self.port = 0

    def __enter__(self) -> Recording:
        self.port = self.proc.start()[1]
        return self

    def __exit__(self, *exc: Any) -> None:
        self.proc.stop()
        self.proc.join(10.0)

    @property
    def reads(self) -> list[bytes]:
        return list(self.recorder.reads)

    @property
    def upstream(self) -> str:
        return self.proc.config.upstream


def with_ticks(reads: list[bytes], every: float = 0.25) -> list[Step]:
    """The reads with a tick after each at the time of its last chunk, and ticks every
    ``every`` s of capture time between them (what the hub's loop would do)."""
    steps: list[Step] = []
    last: float | None = None
    for data in reads:
        steps.append(data)
        t = _last_time(data)
        if t is not None:
            if last is not None:
                x = last + every
                while x < t:
                    steps.append(x)
                    x += every
            steps.append(t + 0.001)
            last = t
    if last is not None:
        steps.append(last + 30.0)  # every request left waits past its timeout
    return steps


def _last_time(data: bytes) -> float | None:
    pos = 0
    last = None
    while pos < len(data):
        if data[pos] == 0x43:
            _tag, _sid, ts, _d, length = CHUNK_HEAD.unpack_from(data, pos)
            last = ts
            pos += CHUNK_HEAD.size + length
        else:
            _tag, length = _OBJECT.unpack_from(data, pos)
            record = pickle.loads(data[pos + _OBJECT.size : pos + _OBJECT.size + length])
            if record[0] == "event":
                last = record[1]
            pos += _OBJECT.size + length
    return last


def recut(steps: list[Step], cuts: list[int]) -> list[Step]:
    """The same bytes and ticks, the bytes between two ticks cut at ``cuts`` (offsets
    into their concatenation, any byte: a read may end mid-record)."""
    out: list[Step] = []
    run = b""
    for step in steps:
        if isinstance(step, float):
            out.extend(_cut(run, cuts))
            run = b""
            out.append(step)
        else:
            run += step
    out.extend(_cut(run, cuts))
    return out


def _cut(data: bytes, cuts: list[int]) -> list[Step]:
    if not data:
        return []
    at = sorted({c % len(data) for c in cuts} - {0})
    parts = []
    prev = 0
    for c in at:
        parts.append(data[prev:c])
        prev = c
    parts.append(data[prev:])
    return [p for p in parts if p]
