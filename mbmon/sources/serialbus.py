"""One RS485 bus tapped through one or two serial ports, as a live source of the hub.

:class:`SerialBusSource` implements the source contract
(:mod:`mbmon.sources.base`) over the pieces of :mod:`mbmon.sources.serial`: one
:class:`~mbmon.sources.serial.SerialTap` thread per port, whose reads become
chunks of ONE bus stream (two one-direction taps are merged by timestamp in a
:class:`~mbmon.sources.serial.TimeMerge` ticker, which runs in the hub's
thread), and a :class:`~mbmon.sources.serial.BusHealth` listener that watches
the bus and reports its figures. It owns the deliver closures, the notices of a
port that is lost and back, the screen's figures, the closing ``STATS`` event and
the summary lines; ``sniff --serial`` only builds it.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

from mbmon.hub import Hub
from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.sources.base import BaseSource, SourceError, SourceMode
from mbmon.sources.serial import BusHealth, SerialSettings, SerialTap, TimeMerge

__all__ = ["SerialBusSource", "SerialOpenError"]

#: The reader threads stamp a read when they hold the GIL again: the default 5 ms
#: switch interval would blur read times (and the gap figures) by up to 5 ms.
SWITCH_INTERVAL = 0.001


class SerialOpenError(SourceError):
    """A port of the bus cannot be opened: which one, and the system's reason."""

    def __init__(self, port: str, exc: OSError) -> None:
        super().__init__(f"cannot open serial port {port}: {exc.strerror or exc}")
        self.port = port
        self.error = exc


class SerialBusSource(BaseSource):
    """One bus stream from ``ports`` (one tap, or two one-direction taps merged by time)."""

    mode: SourceMode = "live"

    def __init__(
        self,
        ports: Sequence[str],
        settings: SerialSettings,
        *,
        merge_window: float = 0.05,
        retry: float = 0.5,
    ) -> None:
        super().__init__()
        if not 1 <= len(ports) <= 2:
            raise ValueError("a bus is tapped through one or two serial ports")
        self.ports = list(ports)
        self.settings = settings
        self.merge_window = merge_window
        self.retry = retry
        self.name = "+".join(self.ports)
        self.taps: list[SerialTap] = []
        self.merge: TimeMerge | None = None
        self.health: BusHealth | None = None
        self.stream: Stream | None = None

    def open(self, hub: Hub) -> None:
        """Open every port (none is left open when one fails: :class:`SerialOpenError`),
        take the bus's stream id, and attach the bus health listener."""
        super().open(hub)
        sys.setswitchinterval(SWITCH_INTERVAL)
        stream = self.stream = hub.new_stream(Transport.RTU, self.name, self.name)
        bus = Direction.BUS

        def notice(ts: float, message: str) -> None:
            hub.put(Event(ts, stream, EventKind.NOTICE, {"message": message}))

        if len(self.ports) == 1:

            def deliver(ts: float, data: bytes) -> None:
                hub.put(Chunk(ts, stream, bus, data))

        else:
            merge = self.merge = TimeMerge(self.merge_window)

            def deliver(ts: float, data: bytes) -> None:
                chunk = Chunk(ts, stream, bus, data)
                hub.submit(lambda: merge.add(chunk))

        for port in self.ports:
            tap = SerialTap(port, self.settings, deliver, notice, retry=self.retry)
            try:
                tap.open()
            except OSError as exc:
                self.stop()
                raise SerialOpenError(port, exc) from None
            self.taps.append(tap)
        if self.merge is not None:
            hub.add_ticker(self.merge)
        self.health = BusHealth(stream, self.settings, hub.put)
        hub.add_listener(self.health)

    def start(self) -> None:
        """Start every tap's reader thread."""
        for tap in self.taps:
            tap.start()

    def stop(self) -> None:
        """Stop the reader threads and close the ports (idempotent)."""
        for tap in self.taps:
            tap.stop()

    def describe(self) -> str:
        """The line settings, for the banner (``115200 8N1``)."""
        return self.settings.text()

    def stats(self) -> dict[str, Any]:
        """The bus health figures the live screen's header shows."""
        return self.health.screen_figures() if self.health is not None else {}

    def closing(self, ts: float) -> list[Event]:
        """The bus health figures as a ``STATS`` event (the log says how the bus was)."""
        return [self.health.stats_event(ts)] if self.health is not None else []

    def summary(self) -> list[str]:
        """What each port read, then the bus health lines."""
        lines = [
            f"{tap.port}: {tap.reads} reads, {tap.bytes} bytes"
            + (f", lost {tap.losses} times" if tap.losses else "")
            for tap in self.taps
        ]
        if self.health is not None:
            lines.extend(self.health.summary())
        return lines
