"""Live serial capture (RS485, Modbus RTU): pyserial reader threads and bus health.

:class:`SerialTap` owns one port: a thread that opens it with pyserial (which
sets speed, parity, stop bits and byte size), then reads its file descriptor
with ``select`` + ``os.read`` and timestamps every read the moment it returns.
Each read becomes a ``Chunk(ts, stream, Direction.BUS, data)`` for the hub; the
RTU bus decoder (:mod:`mbmon.protocol.rtu`) frames by length prediction and
CRC, so bursty USB delivery does not break it. A port that disappears (USB
unplugged, pty closed) is reported and reopened every ``retry`` seconds until
it returns or the run stops.

Two one-direction taps (``--serial A --serial B``: one adapter on the master's
TX pair, one on the slaves') feed ONE bus stream: :class:`TimeMerge` holds the
reads of both for ``window`` seconds and releases them in timestamp order, so
the decoder sees the bus as a single adapter would. Limits: reads are ordered,
not bytes; when one adapter delivers later than the other by more than the
window (or a read of one straddles a frame of the other), the frames involved
become noise until the decoder resynchronises on the next CRC.

:class:`BusHealth` is a hub listener that turns reads and records into health
figures: noise bytes, CRC failures, t3.5 violations, an inter-frame gap
histogram, how the adapter delivers bytes (bursts of ~16 ms make timing
useless) and a noise warning that names a likely wrong baud rate. It reports
them as STATS and NOTICE events (``/mbmon/events`` in a log) and as summary lines.

pyserial is imported only when a port is opened: ``import mbmon`` stays light.
"""

from __future__ import annotations

import errno
import heapq
import os
import select
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mbmon.model import Chunk, Direction, Event, EventKind, Record, RecordKind, Stream
from mbmon.protocol.rtu import t35
from mbmon.sources import DEFAULT_BAUD

__all__ = ["GAP_BUCKETS", "BusHealth", "SerialSettings", "SerialTap", "TimeMerge", "open_port"]


@dataclass(frozen=True, slots=True)
class SerialSettings:
    """Line settings of a tapped RS485 bus."""

    baudrate: int = DEFAULT_BAUD
    parity: str = "N"  # N, E, O
    stopbits: int = 1
    bytesize: int = 8

    def text(self) -> str:
        return f"{self.baudrate} {self.bytesize}{self.parity}{self.stopbits}"

    def char_time(self) -> float:
        """Seconds per character on the wire (start + data + parity + stop bits)."""
        bits = 1 + self.bytesize + (0 if self.parity == "N" else 1) + self.stopbits
        return bits / self.baudrate


def open_port(port: str, settings: SerialSettings) -> Any:
    """A pyserial port opened with ``settings``, non-blocking (``timeout=0``); raises
    ``OSError`` with the system's reason (or the bad setting) when it cannot be."""
    import serial  # type: ignore[import-untyped]  # pyserial ships no types

    s = settings
    try:
        return serial.Serial(
            port,
            baudrate=s.baudrate,
            parity=s.parity,
            stopbits=s.stopbits,
            bytesize=s.bytesize,
            timeout=0,
            exclusive=False,
        )
    except serial.SerialException as exc:
        inner = exc.__context__ if isinstance(exc.__context__, OSError) else None
        if inner is not None:
            raise inner from None
        if "Inappropriate ioctl" in str(exc):  # termios refused it: a file, /dev/null...
            raise OSError(errno.ENOTTY, "not a serial port (it takes no line settings)") from None
        raise OSError(str(exc)) from None
    except ValueError as exc:
        raise OSError(f"bad serial settings: {exc}") from None


class SerialTap:
    """One serial port read by one thread; every read is timestamped and delivered.

    ``deliver(ts, data)`` and ``notice(ts, message)`` are called in the reader
    thread. Opening failures of the first attempt are raised by :meth:`open`
    (a wrong name or missing permission is a usage problem); later losses are
    reported through ``notice`` and retried every ``retry`` seconds.
    """

    def __init__(
        self,
        port: str,
        settings: SerialSettings,
        deliver: Callable[[float, bytes], None],
        notice: Callable[[float, str], None],
        *,
        retry: float = 0.5,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.port = port
        self.settings = settings
        self._deliver = deliver
        self._notice = notice
        self.retry = retry
        self._clock = clock
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._serial: Any = None
        self.reads = 0
        self.bytes = 0
        self.losses = 0

    def open(self) -> None:
        """Open the port now; raise ``OSError`` with the system's reason when it cannot be."""
        self._serial = self._open()

    def _open(self) -> Any:
        return open_port(self.port, self.settings)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"serial {self.port}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._close()

    def _close(self) -> None:
        if self._serial is not None:
            try:
                self._serial.close()
            except Exception:
                pass
            self._serial = None

    def _run(self) -> None:
        stop = self._stop
        clock = self._clock
        while not stop.is_set():
            if self._serial is None:
                try:
                    self._serial = self._open()
                except OSError:
                    stop.wait(self.retry)
                    continue
                self._notice(clock(), f"serial port {self.port} is back")
            fd = self._serial.fileno()
            try:
                while not stop.is_set():
                    ready, _, _ = select.select([fd], [], [], 0.2)
                    if not ready:
                        continue
                    data = os.read(fd, 4096)
                    ts = clock()
                    if not data:
                        raise OSError("end of file")
                    self.reads += 1
                    self.bytes += len(data)
                    self._deliver(ts, data)
            except (OSError, ValueError) as exc:
                self.losses += 1
                self._close()
                reason = getattr(exc, "strerror", None) or str(exc)
                self._notice(
                    clock(),
                    f"serial port {self.port} lost ({reason}); retrying every {self.retry:g} s",
                )
        self._close()


class TimeMerge:
    """Reads of several one-direction taps merged into one bus stream by timestamp.

    A hub ticker: :meth:`add` (run in the hub's thread through ``hub.submit``)
    holds a chunk for ``window`` seconds; :meth:`tick` releases every chunk older
    than ``now - window`` in timestamp order; :meth:`finish` releases the rest.
    """

    def __init__(self, window: float = 0.05, clock: Callable[[], float] = time.time) -> None:
        self.window = window
        self._clock = clock
        self._heap: list[tuple[float, int, Chunk]] = []
        self._seq = 0
        self.late = 0  # chunks that arrived after a newer one had been released

    def add(self, chunk: Chunk) -> list[Chunk | Event]:
        self._seq += 1
        heapq.heappush(self._heap, (chunk.ts, self._seq, chunk))
        return self.tick(self._clock())

    def tick(self, now: float) -> list[Chunk | Event]:
        out: list[Chunk | Event] = []
        limit = now - self.window
        heap = self._heap
        while heap and heap[0][0] <= limit:
            out.append(heapq.heappop(heap)[2])
        return out

    def next_deadline(self) -> float | None:
        return self._heap[0][0] + self.window if self._heap else None

    def finish(self, ts: float) -> list[Chunk | Event]:
        out: list[Chunk | Event] = []
        while self._heap:
            out.append(heapq.heappop(self._heap)[2])
        return out


#: Upper bounds (seconds) of the inter-frame gap histogram; the first bin is "< t3.5".
GAP_BUCKETS: tuple[float, ...] = (0.002, 0.005, 0.010, 0.050, 0.200, 1.0)
#: Figures are reported as a STATS event at most this often (seconds).
STATS_EVERY = 10.0
#: Reads needed before the delivery pattern is judged.
_MIN_READS = 20
#: Bytes needed before the noise share is judged.
_MIN_BYTES = 256


class BusHealth:
    """Health figures of one RTU bus, from the reads (chunks) and the records.

    * ``noise_bytes``, ``crc_errors``: from NOISE records (their reason says bad CRC).
    * inter-frame gaps: a frame ends at its read's timestamp and starts
      ``len * char_time`` earlier; the gap to the previous frame's end goes into
      :data:`GAP_BUCKETS`. Frames completed by the same read have no measurable
      gap (counted as ``same_read``).
    * ``t35_violations``: measurable gaps shorter than t3.5 (only meaningful when
      the adapter delivers bytes promptly).
    * delivery: the median interval of consecutive reads while bytes flow; when it
      is well above t3.5 (an FTDI adapter's 16 ms latency timer) timing figures
      are useless and a NOTICE says so, once.
    * a NOTICE naming a likely wrong baud rate when most bytes are noise.

    ``emit(event)`` queues an event to the hub (``hub.put``); it is called from
    the hub's thread, so the event is fed on the loop's next turn.
    """

    name = "bus health"

    def __init__(
        self,
        stream: Stream,
        settings: SerialSettings,
        emit: Callable[[Event], None],
        *,
        stats_every: float = STATS_EVERY,
    ) -> None:
        self.stream = stream
        self.settings = settings
        self._emit = emit
        self.stats_every = stats_every
        self.char = settings.char_time()
        self.t35 = t35(settings.baudrate)
        self.reads = 0
        self.bytes = 0
        self.frames = 0
        self.noise_bytes = 0
        self.noise_runs = 0
        self.crc_errors = 0
        self.t35_violations = 0
        self.same_read = 0
        self.gaps = [0] * (len(GAP_BUCKETS) + 2)  # < t3.5, each bound, above the last
        self._intervals: deque[float] = deque(maxlen=200)
        self._last_read: float | None = None
        self._last_end: float | None = None
        self._last_end_read = -1
        self._next_stats: float | None = None
        self._changed = False
        self.warned_bursts = False
        self.warned_noise = False
        self.notices: list[str] = []

    # ------------------------------------------------------------------ hooks

    def on_chunk(self, chunk: Chunk) -> None:
        if chunk.stream.id != self.stream.id:
            return
        self.reads += 1
        self.bytes += len(chunk.data)
        last = self._last_read
        if last is not None:
            interval = chunk.ts - last
            if 0 <= interval < 0.1:  # bytes keep flowing: the adapter's delivery rhythm
                self._intervals.append(interval)
        self._last_read = chunk.ts
        self._changed = True

    def on_records(self, records: list[Record]) -> None:
        sid = self.stream.id
        for record in records:
            if record.stream is None or record.stream.id != sid:
                continue
            kind = record.kind
            if record.frame is not None and kind in _FRAME_KINDS:
                self._frame(record.frame.ts, len(record.frame.raw))
            elif kind is RecordKind.NOISE and record.noise is not None:
                self.noise_runs += 1
                self.noise_bytes += len(record.noise.raw)
                if "CRC" in record.noise.reason:
                    self.crc_errors += 1

    def on_tick(self, now: float) -> None:
        self._judge(now)
        if self._next_stats is None:
            self._next_stats = now + self.stats_every
        elif now >= self._next_stats:
            self._next_stats = now + self.stats_every
            if self._changed:
                self._changed = False
                self._emit(self.stats_event(now))

    # ------------------------------------------------------------------ figures

    def _frame(self, ts: float, size: int) -> None:
        self.frames += 1
        start = ts - size * self.char
        read = self.reads
        if self._last_end is not None:
            if read == self._last_end_read:
                self.same_read += 1
            else:
                gap = start - self._last_end
                if gap < self.t35:
                    self.t35_violations += 1
                    self.gaps[0] += 1
                else:
                    for i, bound in enumerate(GAP_BUCKETS):
                        if gap < bound:
                            self.gaps[i + 1] += 1
                            break
                    else:
                        self.gaps[-1] += 1
        self._last_end = ts
        self._last_end_read = read

    def delivery_interval(self) -> float | None:
        """Median interval between reads while bytes flow, or ``None`` before enough reads."""
        if len(self._intervals) < _MIN_READS:
            return None
        return statistics.median(self._intervals)

    def bursty(self) -> bool:
        """Reads arrive in bursts far apart compared with t3.5: silence timing is useless."""
        median = self.delivery_interval()
        return median is not None and median > max(4 * self.t35, 0.008)

    def _judge(self, now: float) -> None:
        if not self.warned_bursts and self.bursty():
            self.warned_bursts = True
            median = self.delivery_interval() or 0.0
            self._notice(
                now,
                f"{self.stream.server}: reads arrive in bursts about {median * 1000:.0f} ms "
                f"apart (USB adapter latency; t3.5 is {self.t35 * 1000:.2f} ms): silence "
                "gaps and t3.5 figures are not meaningful; frames are still found by "
                "length and CRC (FTDI: set latency_timer to 1)",
            )
        if not self.warned_noise and self.bytes >= _MIN_BYTES and self.noise_bytes * 2 > self.bytes:
            self.warned_noise = True
            self._notice(
                now,
                f"{self.stream.server}: {self.noise_bytes} of {self.bytes} bytes are noise "
                f"({self.frames} frames): likely a wrong baud rate or parity "
                f"(listening at {self.settings.text()}; try the bus's rate, e.g. "
                "9600, 19200, 38400, 57600, 115200), or a swapped A/B pair",
            )

    def _notice(self, ts: float, message: str) -> None:
        self.notices.append(message)
        self._emit(Event(ts, self.stream, EventKind.NOTICE, {"message": message}))

    def figures(self) -> dict[str, Any]:
        """The health figures, flat, as a STATS event carries them."""
        median = self.delivery_interval()
        figures: dict[str, Any] = {
            "bus": self.stream.server,
            "reads": self.reads,
            "bytes": self.bytes,
            "frames": self.frames,
            "noise_bytes": self.noise_bytes,
            "crc_errors": self.crc_errors,
            "t35_violations": self.t35_violations,
            "read_interval_ms": round(median * 1000, 2) if median is not None else None,
            "timing_useful": not self.bursty(),
        }
        for label, count in zip(self.gap_labels(), self.gaps, strict=True):
            figures[f"gap_{label}"] = count
        figures["gap_same_read"] = self.same_read
        return figures

    def gap_labels(self) -> list[str]:
        labels = ["lt_t35"]
        labels.extend(f"lt_{bound * 1000:g}ms" for bound in GAP_BUCKETS)
        labels.append(f"ge_{GAP_BUCKETS[-1] * 1000:g}ms")
        return labels

    def screen_figures(self) -> dict[str, Any]:
        """The figures the live screen's header shows for the bus (``sniff`` hands
        them to :meth:`~mbmon.monitor.feed.MonitorFeed.set_figures` on every tick): CRC
        failures, t3.5 violations, the gap histogram, the adapter's read rhythm and,
        once a warning was given, what it was about (the notice itself scrolls away)."""
        figures: dict[str, Any] = {
            "CRC failures": self.crc_errors,
            "t3.5 violations": self.t35_violations,
        }
        hist = " ".join(
            f"{_gap_text(label)}:{count}"
            for label, count in zip(self.gap_labels(), self.gaps, strict=True)
            if count
        )
        figures["gaps"] = hist or "—"
        median = self.delivery_interval()
        if median is not None:
            figures["reads every"] = f"{median * 1000:.1f} ms"
        warnings = []
        if self.warned_bursts:
            warnings.append("adapter bursts: timing not meaningful")
        if self.warned_noise:
            warnings.append("mostly noise: wrong baud rate or parity?")
        if warnings:
            figures["warnings"] = "; ".join(warnings)
        return figures

    def stats_event(self, ts: float) -> Event:
        return Event(ts, self.stream, EventKind.STATS, self.figures())

    def summary(self) -> list[str]:
        """Summary lines for stderr."""
        median = self.delivery_interval()
        lines = [
            f"bus {self.stream.server} ({self.settings.text()}): {self.reads} reads, "
            f"{self.bytes} bytes, {self.frames} frames, {self.noise_bytes} noise bytes, "
            f"{self.crc_errors} CRC failures, {self.t35_violations} t3.5 violations",
        ]
        hist = ", ".join(
            f"{_gap_text(label)}: {count}"
            for label, count in zip(self.gap_labels(), self.gaps, strict=True)
            if count
        )
        lines.append(
            "  inter-frame gaps: "
            + (hist or "none measured")
            + (f" (+{self.same_read} in one read)" if self.same_read else "")
        )
        if median is not None:
            lines.append(
                f"  reads every {median * 1000:.1f} ms while bytes flow"
                + ("; timing NOT meaningful (adapter bursts)" if self.bursty() else "")
            )
        lines.extend(f"  warning: {n}" for n in self.notices)
        return lines


def _gap_text(label: str) -> str:
    """``lt_5ms`` -> ``<5ms``, ``ge_1000ms`` -> ``>=1000ms``, ``lt_t35`` -> ``<t3.5``."""
    if label == "lt_t35":
        return "<t3.5"
    return ("<" if label.startswith("lt_") else ">=") + label[3:]


_FRAME_KINDS = frozenset({RecordKind.REQUEST, RecordKind.RESPONSE, RecordKind.EXCEPTION})


def bus_chunk(stream: Stream, ts: float, data: bytes) -> Chunk:
    """A serial read as the hub takes it: both directions on one bus stream."""
    return Chunk(ts, stream, Direction.BUS, data)
