"""The proxy's serial (RS485, Modbus RTU) sides: an RTU slave bus as the upstream, an
RTU master's port as the client side.

Three variants are built from two pieces plugged into the one
:class:`~mbmon.proxy.engine.ProxyEngine` (its guard, its client logic, its
gateway rules and its observer):

* :class:`RtuLink` -- the upstream is an RTU slave on a serial port (the proxy
  is the bus master). Every client's request becomes an RTU ADU (unit id + PDU +
  CRC), goes on the bus **one at a time** (the bus has one master and one
  request in flight) and its answer goes back to the client as Modbus/TCP with
  the client's own transaction id. Requests wait in one queue per client and
  are taken round robin, so a client that pipelines many requests cannot
  starve the others. An answer is the frame from the asked unit with the asked
  function code (or its exception); anything else on the bus is dropped and
  logged. No answer within ``timeout`` of the request leaving the port: 0x0B
  (the answer that comes later is dropped); the port unavailable (not opened,
  unplugged): 0x0A, the port is reopened every ``retry`` seconds. A broadcast
  (unit 0) is sent and never answered; the next request waits ``turnaround``.
* :class:`RtuFront` -- the clients' side is an RTU master on a serial port (the
  proxy answers as the RTU slave). Each request frame is guarded (a refused
  write gets the RTU exception frame, with CRC, from the proxy), then forwarded
  as Modbus/TCP through the engine's link (a TCP upstream, or an
  :class:`RtuLink`). The gateway's own 0x0A/0x0B are never sent to the master:
  it gets silence, as from an RTU slave that is not there, and the run logs why.
  A new request from the master abandons the one still waiting (an RTU master
  has one request in flight; it has given up on the older one).

Both framings use :class:`~mbmon.protocol.rtu.RtuDecoder` (length prediction +
CRC): requests only on the master's port, answers only on the slave's. Writes
keep the RTU silence (t3.5 from the last byte on the line) before every frame.

What the hub sees: each serial port is one RTU bus stream (``Direction.BUS``
chunks of the bytes read and written, in order), as ``mbmon sniff --serial``
would see that bus; with a TCP upstream behind an RTU master, the Modbus/TCP
requests and answers exchanged with it as one TCP stream; guard decisions and
every gateway decision (silence, late or stray answers, port lost and back) as
events.

Each port is a :class:`~mbmon.proxy.serial_line.SerialLine`; pyserial is imported
when a port is opened (:func:`mbmon.sources.serial.open_port`).
"""

from __future__ import annotations

import asyncio
import struct
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any

from mbmon.model import Direction, EventKind, Frame, Stream, Transport
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.rtu import RtuDecoder, encode_rtu
from mbmon.proxy.client import Client
from mbmon.proxy.config import GATEWAY_PATH_UNAVAILABLE, GATEWAY_TARGET_FAILED
from mbmon.proxy.engine import ProxyEngine
from mbmon.proxy.link import Pending
from mbmon.proxy.serial_line import SETTLE, SerialLine, settle_later
from mbmon.proxy.upstream import TcpLink
from mbmon.sources.serial import SerialSettings

__all__ = ["RtuFront", "RtuLink", "rtu_front", "rtu_upstream"]

_BUS = Direction.BUS
_C2S = Direction.C2S
_S2C = Direction.S2C


# --------------------------------------------------------------------------- upstream


class _Job:
    """One request waiting for, or on, the RTU bus."""

    __slots__ = ("adu", "entry", "fc", "unit")

    def __init__(self, entry: Pending) -> None:
        self.entry = entry
        self.unit = entry.unit
        self.fc = entry.fc
        self.adu = encode_rtu(entry.unit, entry.raw[7:])  # MBAP header off, CRC on


class RtuLink:
    """The upstream is an RTU slave bus: the link every client shares (see the module
    text). It speaks the engine's link protocol (:class:`~mbmon.proxy.link.Link`:
    ``submit``, ``forget``, ``close``...) so the engine's clients -- TCP clients or
    an :class:`RtuFront` -- use it as they use a TCP upstream."""

    owner = None
    remap = False
    next_attempt = 0.0

    def __init__(
        self,
        engine: ProxyEngine,
        port: str,
        settings: SerialSettings,
        *,
        turnaround: float = 0.1,
        retry: float = 0.5,
    ) -> None:
        self.engine = engine
        self.name = port
        self.settings = settings
        self.turnaround = turnaround
        self.stream: Stream = engine.observer.new_stream(Transport.RTU, port, port)
        self.decoder = RtuDecoder(self.stream, _S2C, settings.baudrate, silence=SETTLE)
        self.queues: OrderedDict[Any, deque[_Job]] = OrderedDict()
        self.jobs: dict[Pending, _Job] = {}
        self.current: _Job | None = None
        self.late: tuple[int, int] | None = None  # (unit, fc) answered 0x0B already
        self._timer: asyncio.TimerHandle | None = None
        self._settle: asyncio.TimerHandle | None = None
        self._next: asyncio.TimerHandle | None = None
        self.line = SerialLine(
            engine.loop, port, settings, self._data, self._line_state, retry=retry
        )
        self.line.open()  # raises OSError: the command says it cannot open the port
        engine.upstream_state = "up"

    # -------------------------------------------------------------- the engine's link API

    @property
    def state(self) -> str:
        return "up" if self.line.state == "up" else self.line.state

    def connect(self) -> None:
        """The port reopens by itself (:class:`SerialLine`)."""

    def assign_tid(self, tid: int) -> int:
        return tid  # transaction ids never reach the bus: the client's own comes back

    def write(self, data: bytes) -> None:
        """Unused: :meth:`submit` puts requests on the bus itself."""

    def submit(self, entry: Pending) -> bytes | None:
        """Queue ``entry`` for the bus (0x0A at once when the port is unavailable)."""
        if self.line.state != "up":
            self.engine.answer_exception(entry, GATEWAY_PATH_UNAVAILABLE)
            return None
        entry.link = self  # type: ignore[assignment]
        entry.client.outstanding.add(entry)
        job = _Job(entry)
        self.jobs[entry] = job
        queue = self.queues.get(entry.client)
        if queue is None:
            self.queues[entry.client] = deque((job,))
        else:
            queue.append(job)
        if self.current is None and self._next is None:
            self._start()
        return None

    def forget(self, entry: Pending, why: str | None = None) -> None:
        """Stop waiting for ``entry`` (its client left): out of the queue, or its
        answer, when it comes, is dropped."""
        job = self.jobs.pop(entry, None)
        entry.done = True
        if job is None:
            return
        if job is self.current:
            self._give_up(job, why or "forgotten")
            return
        queue = self.queues.get(entry.client)
        if queue is not None and job in queue:
            queue.remove(job)
            if not queue:
                del self.queues[entry.client]

    def close(self) -> None:
        for handle in (self._timer, self._settle, self._next):
            if handle is not None:
                handle.cancel()
        self._timer = self._settle = self._next = None
        for entry in list(self.jobs):
            entry.done = True
        self.jobs.clear()
        self.queues.clear()
        self.current = None
        self.line.close()

    # -------------------------------------------------------------- the bus

    def _take(self) -> _Job | None:
        """The next job, round robin over the clients' queues."""
        queues = self.queues
        while queues:
            client, queue = next(iter(queues.items()))
            job = queue.popleft()
            if queue:
                queues.move_to_end(client)
            else:
                del queues[client]
            if job.entry in self.jobs:
                return job
        return None

    def _start(self) -> None:
        self._next = None
        if self.current is not None or self.line.state != "up":
            return
        job = self._take()
        if job is None:
            return
        self.current = job
        if self.late is not None:
            # the bytes of an answer given up on are no part of the next one; an answer
            # later still cannot be told from the next one's (RTU has no transaction
            # id): --timeout must be longer than the slowest slave's answer
            self.decoder.reset(time.time())
            self.late = None
        self.line.write(job.adu, self._sent)

    def _sent(self, adu: bytes, ts: float) -> None:
        job = self.current
        self.engine.observer.chunk(self.stream, _BUS, adu, ts)
        if job is None or job.adu is not adu:
            return
        if job.unit == 0:  # broadcast: no slave answers; the bus rests turnaround
            self._finish(job)
            self.jobs.pop(job.entry, None)
            client = job.entry.client
            client.outstanding.discard(job.entry)
            client.flush()  # an answer of the proxy's held behind it may go
            self._next = self.engine.loop.call_later(self.turnaround, self._start)
            return
        self._timer = self.engine.loop.call_later(self.engine.config.timeout, self._expire)

    def _finish(self, job: _Job) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self.current is job:
            self.current = None

    def _next_soon(self) -> None:
        if self._next is None:
            self._next = self.engine.loop.call_soon(self._start)  # type: ignore[assignment]

    def _expire(self) -> None:
        """No answer in time: 0x0B; an answer that comes later is dropped."""
        self._timer = None
        job = self.current
        if job is None:
            return
        self.current = None
        self.late = (job.unit, job.fc)
        entry = job.entry
        self.jobs.pop(entry, None)
        entry.done = True
        client = entry.client
        if not client.closed:
            client.notice(
                f"no answer from RTU unit {job.unit} on {self.name} within "
                f"{self.engine.config.timeout:g} s to tid {entry.tid}"
                + ("" if client.silent else ": answered 0x0B"),
                {"tid": entry.tid, "fc": job.fc, "unit": job.unit},
            )
        self.engine.answer_exception(entry, GATEWAY_TARGET_FAILED)
        self._next_soon()

    def _give_up(self, job: _Job, why: str) -> None:
        """The job on the bus is no longer wanted: its answer will be dropped."""
        self._finish(job)
        self.late = (job.unit, job.fc)
        self._next_soon()

    def _data(self, data: bytes, ts: float) -> None:
        self.engine.observer.chunk(self.stream, _BUS, data, ts)
        self._decoded(self.decoder.feed(data, ts))
        self._settle = settle_later(self.engine.loop, self.decoder, self._settle, self._tick)

    def _tick(self) -> None:
        self._settle = None
        self._decoded(self.decoder.tick(time.time()))
        self._settle = settle_later(self.engine.loop, self.decoder, self._settle, self._tick)

    def _decoded(self, items: list[Any]) -> None:
        for item in items:
            if type(item) is not Frame:
                continue  # noise: the hub's own decoding of the bus reports it
            job = self.current
            raw = item.raw
            unit, fc = raw[0], raw[1] & 0x7F
            if job is not None and unit == job.unit and fc == job.fc:
                self._answer(job, raw, item.ts)
                continue
            engine = self.engine
            if self.late == (unit, fc):
                self.late = None
                engine.stats.late_dropped += 1
                why = "late answer (answered 0x0B already)"
            else:
                engine.stats.unmatched_dropped += 1
                why = "answer nobody is waiting for"
            engine.observer.event(
                self.stream,
                EventKind.NOTICE,
                {
                    "message": f"{why} from RTU unit {unit} on {self.name} dropped",
                    "unit": unit,
                    "raw": raw.hex(" ").upper(),
                },
            )

    def _answer(self, job: _Job, raw: bytes, ts: float) -> None:
        self._finish(job)
        entry = job.entry
        self.jobs.pop(entry, None)
        entry.done = True
        client = entry.client
        client.outstanding.discard(entry)
        self.engine.stats.responses += 1
        if not client.closed:
            client.send(encode_adu(entry.tid, entry.unit, raw[1:-2]), ts)
        self._next_soon()

    def _line_state(self, up: bool, why: str) -> None:
        engine = self.engine
        engine.upstream_state = "up" if up else f"unavailable ({why})"
        if not up:
            engine.stats.upstream_failures += 1
        else:
            engine.stats.upstream_connects += 1
        engine.observer.event(
            self.stream,
            EventKind.NOTICE,
            {
                "message": why + ("" if up else ": answering 0x0A until it is back"),
                "upstream": self.name,
            },
        )
        if up:
            self.decoder.reset(time.time())
            self._next_soon()
            return
        # everything waiting, and the request on the bus, is answered 0x0A
        if self.current is not None:
            self._finish(self.current)
        waiting = [job for queue in self.queues.values() for job in queue]
        self.queues.clear()
        for job in waiting:
            if self.jobs.pop(job.entry, None) is not None:
                job.entry.done = True
                engine.answer_exception(job.entry, GATEWAY_PATH_UNAVAILABLE)
        for entry in list(self.jobs):
            entry.done = True
            engine.answer_exception(entry, GATEWAY_PATH_UNAVAILABLE)
        self.jobs.clear()


# --------------------------------------------------------------------------- the master side


class RtuFront(Client):
    """The client side is an RTU master on a serial port; the proxy answers as its
    RTU slave (see the module text). One engine client, silent to gateway failures."""

    silent = True
    streams_answers = False  # whole answers, made into RTU frames by :meth:`send`

    def __init__(self, engine: ProxyEngine, port: str, settings: SerialSettings) -> None:
        super().__init__(engine)
        self.name = port
        self.settings = settings
        self.peer = port
        observer = engine.observer
        #: the master's bus, as a tap on it would see it
        self.bus: Stream = observer.new_stream(Transport.RTU, port, port)
        self.stream = self.bus  # events (guard, notices) belong to the master's bus
        self.rtu = RtuDecoder(self.bus, _C2S, settings.baudrate, silence=SETTLE)
        self._settle: asyncio.TimerHandle | None = None
        self._refusing = False
        self._tid = 0
        #: the Modbus/TCP side when the upstream is a TCP server (None for an RTU bus)
        self.tcp: Stream | None = None
        self.line = SerialLine(engine.loop, port, settings, self._data, self._line_state)
        self.line.open()  # raises OSError: the command says it cannot open the port
        engine.stats.clients += 1
        engine.clients.add(self)
        observer.event(
            self.bus,
            EventKind.NOTICE,
            {"message": f"answering the RTU master on {port} ({settings.text()})"},
        )
        if engine.shared is not None:
            self.link = engine.shared
        else:
            self.tcp = observer.new_stream(Transport.TCP, port, engine.config.upstream)
            self.link = TcpLink(engine, self)
            self.link.connect()

    # -------------------------------------------------------------- requests

    def _data(self, data: bytes, ts: float) -> None:
        engine = self.engine
        engine.observer.chunk(self.bus, _BUS, data, ts)
        engine.stats.bytes_from_clients += len(data)
        self._decoded(self.rtu.feed(data, ts), ts)
        self._settle = settle_later(engine.loop, self.rtu, self._settle, self._tick)

    def _tick(self) -> None:
        self._settle = None
        self._decoded(self.rtu.tick(time.time()), time.time())
        self._settle = settle_later(self.engine.loop, self.rtu, self._settle, self._tick)

    def _decoded(self, items: list[Any], ts: float) -> None:
        engine = self.engine
        guard = engine.config.guard
        for item in items:
            if type(item) is not Frame:
                continue  # noise: the hub's decoding of the bus reports it
            engine.stats.requests += 1
            link = self.link
            assert link is not None
            for old in list(self.outstanding):  # the master gave up on it
                self.outstanding.discard(old)
                link.forget(old, "the RTU master sent its next request")
            # the request as Modbus/TCP: the engine's clients, links and guard speak it
            self._tid = tid = (self._tid + 1) & 0xFFFF
            raw = item.raw
            mbap = struct.pack(">HHHB", tid, 0, len(raw) - 2, raw[0]) + raw[1:-2]
            if guard.active:
                verdict = guard.check(raw[0], item.pdu)
                if verdict is not None:
                    self._refusing = True
                    try:
                        self.refuse(mbap, verdict.message, verdict.info, ts)
                    finally:
                        self._refusing = False
                    continue
            if self.tcp is not None:
                engine.observer.chunk(self.tcp, _C2S, mbap, ts)
            self.forward([mbap], ts, guarded=True)

    # -------------------------------------------------------------- answers

    def send(self, data: bytes, ts: float) -> None:
        """Answers as Modbus/TCP ADUs (the link's or a guard refusal): to the master as
        RTU frames (none for a broadcast)."""
        if self.closed:
            return
        engine = self.engine
        if self.tcp is not None and not self._refusing:
            engine.observer.chunk(self.tcp, _S2C, data, ts)
        pos = 0
        while pos + 7 <= len(data):
            end = pos + 6 + ((data[pos + 4] << 8) | data[pos + 5])
            unit, pdu = data[pos + 6], data[pos + 7 : end]
            pos = end
            if unit == 0:
                continue  # a broadcast is never answered
            frame = encode_rtu(unit, pdu)
            engine.stats.bytes_to_clients += len(frame)
            self.line.write(frame, self._sent)

    def _sent(self, frame: bytes, ts: float) -> None:
        self.engine.observer.chunk(self.bus, _BUS, frame, ts)

    def unanswered(self, entry: Pending, code: int) -> None:
        why = "upstream unavailable" if code == GATEWAY_PATH_UNAVAILABLE else "no answer in time"
        self.engine.stats.unanswered += 1
        self.notice(
            f"no answer to the RTU master (unit {entry.unit}, fc {entry.fc:02X}): {why}; "
            "silence, as from an RTU slave",
            {"unit": entry.unit, "fc": entry.fc, "gateway_exception": code},
        )

    # -------------------------------------------------------------- lifetime

    def _line_state(self, up: bool, why: str) -> None:
        self.notice(why, {"port": self.name})
        if up:
            self.rtu.reset(time.time())

    def drop(self, reason: str, count: bool = True) -> None:
        """The proxy stops: close the port (the master's side has no connection)."""
        if self.closed:
            return
        self.closed = True
        if self._settle is not None:
            self._settle.cancel()
        self.line.close()
        engine = self.engine
        engine.clients.discard(self)
        link = self.link
        if link is not None:
            for entry in list(self.outstanding):
                link.forget(entry)
            if link.owner is self:
                link.close()
        self.outstanding.clear()
        self.notice(f"RTU master side {self.name} closed: {reason}", {"port": self.name})


def rtu_upstream(port: str, settings: SerialSettings) -> Callable[[ProxyEngine], RtuLink]:
    """The engine's ``upstream`` factory for an RTU slave on ``port``."""
    return lambda engine: RtuLink(engine, port, settings)


def rtu_front(port: str, settings: SerialSettings) -> Callable[[ProxyEngine], RtuFront]:
    """The engine's ``front`` factory for an RTU master on ``port``."""
    return lambda engine: RtuFront(engine, port, settings)
