"""One serial port on the engine's loop, for the proxy's RTU sides
(:mod:`mbmon.proxy.serial`): :class:`SerialLine` opens it (pyserial, through
:func:`mbmon.sources.serial.open_port`), reads it through the loop's reader on its
file descriptor, writes frame by frame with the RTU silence (t3.5) before each,
and reopens a lost port every ``retry`` seconds; :func:`settle_later` arms the
timer that lets an RTU decoder decide the bytes it holds.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from mbmon.protocol.rtu import RtuDecoder, t35
from mbmon.sources.serial import SerialSettings, open_port

__all__ = ["SETTLE", "SerialLine", "SerialOpenError", "settle_later"]

#: Seconds after the last byte at which a decoder decides what it holds (a
#: partial frame becomes noise), whatever the baud rate.
SETTLE = 0.05


class SerialOpenError(OSError):
    """A serial port of the proxy could not be opened at start (the message names it)."""


class SerialLine:
    """One serial port on the engine's loop: opened by pyserial (line settings), read
    through the loop's reader on its file descriptor, written frame by frame with
    the RTU silence before each. A lost port is reported through ``on_state`` and
    reopened every ``retry`` seconds until :meth:`close`.

    ``on_data(data, ts)`` gets every read, stamped when it returned;
    ``on_state(up, why)`` every change of availability.
    """

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        port: str,
        settings: SerialSettings,
        on_data: Callable[[bytes, float], None],
        on_state: Callable[[bool, str], None],
        *,
        retry: float = 0.5,
    ) -> None:
        self.loop = loop
        self.port = port
        self.settings = settings
        self._on_data = on_data
        self._on_state = on_state
        self.retry = retry
        self.state = "down"  # up | down | closed
        self._serial: Any = None
        self._fd = -1
        #: frames to write: [frame, bytes of it written, on_sent]
        self._out: deque[list[Any]] = deque()
        self._quiet_at = 0.0  # loop time from which the line has been silent t3.5
        self._t35 = t35(settings.baudrate)
        self._char = settings.char_time()
        self._pump_handle: asyncio.TimerHandle | None = None
        self._writer = False
        self._retry_handle: asyncio.TimerHandle | None = None

    def open(self) -> None:
        """Open the port now; ``OSError`` with the system's reason when it cannot be."""
        try:
            self._serial = open_port(self.port, self.settings)
        except OSError as exc:
            why = exc.strerror or str(exc)
            raise SerialOpenError(
                exc.errno or 0, f"cannot open serial port {self.port}: {why}"
            ) from None
        self._fd = self._serial.fileno()
        os.set_blocking(self._fd, False)
        self.state = "up"
        self._quiet_at = self.loop.time() + self._t35
        self.loop.add_reader(self._fd, self._readable)

    def write(self, frame: bytes, on_sent: Callable[[bytes, float], None] | None = None) -> None:
        """Send ``frame`` once the line has been silent t3.5; ``on_sent(frame, ts)``
        when it has been written. Dropped (and ``on_sent`` never called) while down."""
        if self.state != "up":
            return
        self._out.append([frame, 0, on_sent])
        if len(self._out) == 1 and self._pump_handle is None and not self._writer:
            self._pump()

    def _pump(self) -> None:
        self._pump_handle = None
        loop = self.loop
        while self._out and self.state == "up":
            wait = self._quiet_at - loop.time()
            if wait > 0:
                self._pump_handle = loop.call_later(wait, self._pump)
                return
            item = self._out[0]
            frame, done, on_sent = item
            try:
                n = os.write(self._fd, frame[done:] if done else frame)
            except BlockingIOError:
                n = 0
            except OSError as exc:
                self._lost(exc)
                return
            if done + n < len(frame):  # the driver's buffer is full: the rest when it drains
                item[1] = done + n
                if not self._writer:
                    self._writer = True
                    loop.add_writer(self._fd, self._writable)
                return
            self._out.popleft()
            self._quiet_at = loop.time() + len(frame) * self._char + self._t35
            if on_sent is not None:
                on_sent(frame, time.time())

    def _writable(self) -> None:
        self._writer = False
        self.loop.remove_writer(self._fd)
        self._pump()

    def _readable(self) -> None:
        try:
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            self._lost(exc)
            return
        if not data:
            self._lost(OSError("end of file"))
            return
        self._quiet_at = self.loop.time() + self._t35
        self._on_data(data, time.time())

    def _detach(self) -> None:
        if self._fd >= 0:
            self.loop.remove_reader(self._fd)
            if self._writer:
                self.loop.remove_writer(self._fd)
                self._writer = False
        if self._pump_handle is not None:
            self._pump_handle.cancel()
            self._pump_handle = None
        self._out.clear()
        if self._serial is not None:
            try:
                self._serial.close()
            except Exception:
                pass
        self._serial = None
        self._fd = -1

    def _lost(self, exc: BaseException) -> None:
        self._detach()
        self.state = "down"
        why = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
        self._on_state(False, f"serial port {self.port} lost ({why})")
        self._retry_handle = self.loop.call_later(self.retry, self._reopen)

    def _reopen(self) -> None:
        self._retry_handle = None
        if self.state != "down":
            return
        try:
            self.open()
        except OSError:
            self._retry_handle = self.loop.call_later(self.retry, self._reopen)
            return
        self._on_state(True, f"serial port {self.port} is back")

    def close(self) -> None:
        self._detach()
        self.state = "closed"
        if self._retry_handle is not None:
            self._retry_handle.cancel()
            self._retry_handle = None


def settle_later(
    loop: asyncio.AbstractEventLoop,
    decoder: RtuDecoder,
    handle: asyncio.TimerHandle | None,
    tick: Callable[[], None],
) -> asyncio.TimerHandle | None:
    """(Re)arm the timer that lets ``decoder`` decide the bytes it holds."""
    if handle is not None:
        handle.cancel()
    deadline = decoder.next_deadline()
    if deadline is None:
        return None
    return loop.call_later(max(0.0, deadline - time.time()), tick)
