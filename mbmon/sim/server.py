"""SimServer: a :class:`~mbmon.sim.robot.SimRobot` served over Modbus/TCP or RTU by pymodbus.

What it owns: the pymodbus server (``ModbusTcpServer`` or ``ModbusSerialServer``
with a ``SimDevice`` whose ``action`` hook hands every access to the robot),
the event loop it runs in (a background thread for :meth:`SimServer.start`, or
the caller's loop for :meth:`SimServer.serve`), the lock around the robot and
the unit filter. pymodbus keeps register blocks of its own; they are only a
mirror the hook refreshes from the robot on every access, so the robot is the
one state.

Function codes: those of the manual's Table 10 (01, 02, 03, 04, 05, 06, 0F,
10); any other is answered with exception 01 and its own function code (``94 01``
for Read File Record), a Table 10 request whose lengths disagree with exception
03. Every request of a TCP segment is answered, in order (pipelined requests:
see :mod:`mbmon.sim.handler`). Unit ids: on TCP a request for
another unit is answered with exception 0x0B (gateway target failed to
respond); on RTU it is left unanswered, as another device on the bus would
answer it; RTU broadcasts (unit 0) are executed and not answered.

Written for pymodbus 3.16 (``pymodbus.simulator.SimDevice`` with ``action``,
``pymodbus.server.ModbusTcpServer``/``ModbusSerialServer`` taking a
``SimDevice``); pyproject.toml pins the range this was tested with.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from mbmon.protocol.functions import FUNCTIONS, PROFILE_TABLE
from mbmon.sim.robot import SimEvent, SimRobot
from mbmon.sim.spec import served_functions
from mbmon.sources import DEFAULT_BAUD

__all__ = ["SimServer"]

#: Table 10 of the manual: the function codes HRSS serves (the ``hrss`` profile's
#: ``functions``); any other is answered exception 01.
FUNCTION_CODES = served_functions()
#: Function code -> register table, as pymodbus hands them to the ``action`` hook
#: (from the one function-code table).
_TABLE_OF_FC: dict[int, str] = {
    fc: PROFILE_TABLE[table] for fc in FUNCTION_CODES if (table := FUNCTIONS[fc].table)
}
#: the bit reads, whose address range the robot checks before pymodbus answers
_BIT_READS = frozenset(fc for fc in FUNCTION_CODES if FUNCTIONS[fc].read and FUNCTIONS[fc].bits)
_EXC_ILLEGAL_FUNCTION = 1
_EXC_ILLEGAL_DATA_VALUE = 3
_EXC_GATEWAY_NO_RESPONSE = 0x0B


class _Refusal:
    """Stands in for a request the robot refuses before pymodbus runs it: answered ``code``."""

    def __init__(self, function_code: int, dev_id: int, transaction_id: int, code: int) -> None:
        self.function_code = function_code & 0x7F
        self.dev_id = dev_id
        self.transaction_id = transaction_id
        self.code = code

    async def datastore_update(self, _context: Any, _dev_id: int) -> Any:
        from pymodbus.pdu import ExceptionResponse

        return ExceptionResponse(self.function_code, self.code)


class SimServer:
    """Serve a simulated HRSS robot.

    ``SimServer()`` listens on 127.0.0.1 at a free port (``port=0``) for TCP;
    ``SimServer(serial="/dev/ttyUSB0", baudrate=..., parity=..., stopbits=...)``
    serves RTU on a serial port instead. ``robot`` defaults to a new
    :class:`SimRobot` on the server's clock (``time.monotonic``).

    Use :meth:`start` / :meth:`stop` (background thread; also a context
    manager) from synchronous code and tests, or ``await serve(stop_event)`` in
    an asyncio program. Read the robot under :attr:`lock`, or use
    :meth:`snapshot`. ``on_packet(sending, data)`` sees every ADU the server
    receives (False) or sends (True), as pymodbus frames them.
    """

    def __init__(
        self,
        robot: SimRobot | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        unit: int = 1,
        serial: str | None = None,
        baudrate: int = DEFAULT_BAUD,
        parity: str = "N",
        stopbits: int = 1,
        clock: Callable[[], float] = time.monotonic,
        on_event: Callable[[SimEvent], None] | None = None,
        on_packet: Callable[[bool, bytes], None] | None = None,
    ) -> None:
        if not 1 <= unit <= 247:
            raise ValueError(f"unit must be 1..247, not {unit}")
        self.clock = clock
        self.robot = robot if robot is not None else SimRobot(clock())
        if on_event is not None:
            self.robot.on_event = on_event
        self.host, self.port, self.unit = host, port, unit
        self.serial, self.baudrate, self.parity, self.stopbits = serial, baudrate, parity, stopbits
        self.on_packet = on_packet
        self.lock = threading.RLock()
        self._server: Any = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None

    # ------------------------------------------------------------------ robot access

    def snapshot(self) -> dict[str, Any]:
        """The robot's state now (see :meth:`SimRobot.state`), taken under the lock."""
        with self.lock:
            self.robot.step(self.clock())
            return self.robot.state()

    def call(self, fn: Callable[[SimRobot, float], Any]) -> Any:
        """Run ``fn(robot, now)`` under the lock (to set DI, raise a fault, ...)."""
        with self.lock:
            now = self.clock()
            self.robot.step(now)
            return fn(self.robot, now)

    @property
    def address(self) -> str:
        """``host:port`` for TCP, the serial port's path for RTU."""
        return self.serial if self.serial else f"{self.host}:{self.port}"

    # ------------------------------------------------------------------ pymodbus glue

    def _device(self) -> Any:
        from pymodbus.simulator import DataType, SimData, SimDevice

        bits, regs = DataType.BITS, DataType.REGISTERS
        n = max(len(self.robot.coils), len(self.robot.discrete))
        off = [False] * (-(-n // 16) * 16)  # bit blocks are whole 16-bit words
        return SimDevice(
            self.unit,
            simdata=(
                [SimData(0, values=off, datatype=bits)],
                [SimData(0, values=list(off), datatype=bits)],
                [SimData(0, count=len(self.robot.holding), values=0, datatype=regs)],
                [SimData(0, count=len(self.robot.inputs), values=0, datatype=regs)],
            ),
            action=self._action,
        )

    async def _action(
        self,
        fc: int,
        start: int,
        address: int,
        count: int,
        registers: list[int],
        values: list[int] | list[bool] | None,
    ) -> Any:
        """pymodbus's hook, before every access: the robot answers, the block mirrors it."""
        from pymodbus.constants import ExcCodes

        table = _TABLE_OF_FC.get(fc)
        if table is None:
            return ExcCodes.ILLEGAL_FUNCTION
        with self.lock:
            now = self.clock()
            if values is not None:
                exc = self.robot.write(table, address, [int(v) for v in values], now)
            elif table in ("coils", "discrete_inputs"):
                exc = None  # bit reads were checked in _trace_pdu (here count is in words)
            else:
                exc = self.robot.check(table, address, count)
            if exc is None:
                self.robot.step(now)
                self._mirror(table, registers)
        if exc is not None:
            return ExcCodes(exc)
        return None

    def _mirror(self, table: str, registers: list[int]) -> None:
        src = self.robot.table(table)
        if table in ("coils", "discrete_inputs"):
            bits = src + [0] * (len(registers) * 16 - len(src))
            for w in range(len(registers) - 1):  # the last word is pymodbus's end marker
                word = 0
                for b in range(16):
                    if bits[16 * w + b]:
                        word |= 1 << b
                registers[w] = word
        else:
            registers[: len(src)] = src  # the block starts at address 0

    def admit(self, pdu: Any, fc: int, dev_id: int, tid: int) -> Any:
        """What answers one request: ``pdu`` itself (the robot runs it), a refusal
        (answered with an exception code), or ``None`` (left unanswered).

        ``pdu`` is pymodbus's decoded request, ``None`` when pymodbus could not
        decode it; ``fc``, ``dev_id`` and ``tid`` come from the ADU. Units are
        filtered first (TCP: another unit is answered 0x0B; RTU: left to the
        device it is for; unit 0 is a broadcast), then function codes: one
        outside Table 10 is answered exception 01 with its own code, whether or
        not pymodbus knows it, and a Table 10 request that does not decode
        (lengths that disagree) exception 03. Bit reads are checked against the
        map here, where their exact count is known (pymodbus hands the
        ``action`` hook a count in 16-bit words).
        """
        if dev_id != self.unit:
            if self.serial is None:
                return _Refusal(fc, dev_id, tid, _EXC_GATEWAY_NO_RESPONSE)
            if dev_id != 0:
                return None  # RTU: a request for another device on the bus
        if fc not in FUNCTION_CODES:
            return _Refusal(fc, dev_id, tid, _EXC_ILLEGAL_FUNCTION)
        if pdu is None:
            return _Refusal(fc, dev_id, tid, _EXC_ILLEGAL_DATA_VALUE)
        if fc in _BIT_READS:
            with self.lock:
                exc = self.robot.check(_TABLE_OF_FC[fc], pdu.address, pdu.count)
            if exc is not None:
                return _Refusal(fc, dev_id, tid, exc)
        return pdu

    def _trace_pdu(self, sending: bool, pdu: Any) -> Any:
        """pymodbus's hook on every PDU: requests it decoded go through :meth:`admit`."""
        if sending:
            return pdu
        return self.admit(pdu, pdu.function_code, pdu.dev_id, pdu.transaction_id)

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if self.on_packet is not None:
            with contextlib.suppress(Exception):
                self.on_packet(sending, bytes(data))
        return data

    async def _open(self) -> None:
        from pymodbus import FramerType

        from mbmon.sim.handler import SimSerialServer, SimTcpServer

        common: dict[str, Any] = {
            "trace_pdu": self._trace_pdu,
            "trace_packet": self._trace_packet,
        }
        if self.serial is None:
            self._server = SimTcpServer(self._device(), address=(self.host, self.port), **common)
        else:
            self._server = SimSerialServer(
                self._device(),
                framer=FramerType.RTU,
                port=self.serial,
                baudrate=self.baudrate,
                parity=self.parity,
                stopbits=self.stopbits,
                broadcast_enable=True,
                **common,
            )
        self._server.sim = self
        # pymodbus swallows the reason ("Could not start listen, please check address."):
        # keep the system's error of the listening socket or serial port it opens
        failures: list[OSError] = []
        create = self._server.call_create

        async def call_create() -> Any:
            try:
                return await create()
            except OSError as exc:
                if self.serial:
                    failures.append(self._serial_reason())
                elif exc.errno:  # asyncio's strerror is a sentence around the address
                    failures.append(OSError(exc.errno, os.strerror(exc.errno)))
                else:
                    failures.append(exc)
                raise

        self._server.call_create = call_create
        try:
            await self._server.serve_forever(background=True)
        except RuntimeError as err:
            if failures:
                exc = failures[-1]
                if exc.errno is None:
                    raise OSError(exc.strerror or str(exc)) from None
                raise OSError(exc.errno, exc.strerror or str(exc), self.address) from None
            raise OSError(f"cannot listen on {self.address}: {err}") from None
        if self.serial is None:
            sock = self._server.transport.sockets[0]
            self.host, self.port = sock.getsockname()[:2]

    def _serial_reason(self) -> OSError:
        """Why the serial port does not open, in the words of mbmon's own serial opener
        (pyserial's exception hides the system's error)."""
        from mbmon.sources.serial import SerialSettings, open_port

        try:
            port = open_port(
                self.serial or "", SerialSettings(self.baudrate, self.parity, self.stopbits)
            )
        except OSError as exc:
            return exc
        port.close()  # it opens now: pymodbus's failure was passing
        return OSError("the serial port could not be opened")

    async def _close(self) -> None:
        if self._server is not None:
            with contextlib.suppress(Exception):
                await self._server.shutdown()
            self._server = None

    # ------------------------------------------------------------------ running

    async def serve(self, stop: asyncio.Event, on_ready: Callable[[], None] | None = None) -> None:
        """Serve in the running loop until ``stop`` is set; ``on_ready`` once listening."""
        await self._open()
        try:
            if on_ready is not None:
                on_ready()
            await stop.wait()
        finally:
            await self._close()

    def start(self, timeout: float = 10.0) -> tuple[str, int] | str:
        """Serve from a background thread; returns ``(host, port)`` (TCP) or the serial port."""
        if self._thread is not None:
            raise RuntimeError("SimServer already started")
        self._thread = threading.Thread(target=self._run, name="mbmon-sim", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            raise TimeoutError(f"sim did not start within {timeout} s")
        if self._error is not None:
            self._thread.join()
            self._thread = None
            raise self._error
        return self.serial if self.serial else (self.host, self.port)

    def _run(self) -> None:
        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            try:
                await self.serve(self._stop, self._ready.set)
            except BaseException as err:  # reported to start()'s caller
                self._error = err
                self._ready.set()

        asyncio.run(main())

    def stop(self, timeout: float = 10.0) -> None:
        """Stop serving and join the thread (idempotent)."""
        thread, loop, stop = self._thread, self._loop, self._stop
        if thread is None:
            return
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        thread.join(timeout)
        self._thread = None

    def __enter__(self) -> SimServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
