"""The sim's side of one connection: ADUs in, answers out, every one and in order.

What it owns: framing what a client sends, turning each request into a PDU the
robot runs or a refusal, and answering each request in the order it arrived.
pymodbus's own request handler answers only the first ADU of a TCP segment
(the rest stay in its buffer, which its next send clears) and answers a request
it cannot decode with function code 0 (``80 01``); this handler keeps
pymodbus's PDUs, datastore and encoder and replaces those two parts:

- **TCP**: pymodbus silently drops a read longer than one ADU (a segment with
  more than about 20 pipelined reads); here every read is taken whole and
  framed by mbmon's own :class:`~mbmon.protocol.mbap.MbapDecoder`
  (any segmentation gives the same ADUs); each ADU is queued and one task per
  connection answers the queue in order, so 20 pipelined requests in one
  segment get 20 answers. Reading pauses while too many requests wait.
- **RTU**: pymodbus's RTU framer, unchanged (a half-duplex bus carries one
  request at a time); a request it cannot decode, or whose function code it
  does not know (CRC-valid bytes it would skip), is answered with its own
  function code.

Which requests are answered how (unit filter, Table 10, malformed requests) is
:meth:`mbmon.sim.server.SimServer.admit`'s decision. Imported only when a sim
starts (it imports pymodbus).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections import deque
from typing import Any, Protocol, cast

from pymodbus.exceptions import ModbusIOException
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.transaction import TransactionManager

from mbmon.model import Direction, Frame, Stream, Transport
from mbmon.protocol.crc import check_crc
from mbmon.protocol.mbap import MbapDecoder


class SimServer(Protocol):
    """What the handler needs of :class:`mbmon.sim.server.SimServer` (which imports
    this module: no import back)."""

    address: str

    def admit(self, pdu: Any, fc: int, dev_id: int, tid: int) -> Any: ...


__all__ = ["MAX_PENDING", "SimSerialServer", "SimTcpServer"]

MAX_PENDING = 256
"""Requests of one connection waiting for their answers before reading pauses."""

READ_LIMIT = 1 << 24
"""Largest single TCP read taken (asyncio reads at most 256 KiB at a time)."""


class _FunctionCodeMemo:
    """pymodbus's PDU decoder, remembering the function code of the last PDU it was given
    (pymodbus reports a PDU it cannot decode without it)."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.last_fc = 0

    def decode(self, frame: bytes) -> ModbusPDU | None:
        self.last_fc = frame[0] if frame else 0
        return self.inner.decode(frame)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


class SimRequestHandler(ServerRequestHandler):
    """One TCP connection, or the serial line, of a :class:`SimServer`."""

    def __init__(self, owner: Any, sim: SimServer, tcp: bool) -> None:
        super().__init__(owner, owner.trace_packet, owner.trace_pdu, owner.trace_connect)
        self.sim = sim
        self._memo = _FunctionCodeMemo(self.framer.decoder)
        self.framer.decoder = cast(DecodePDU, self._memo)  # it stands in for one
        self._mbap = (
            MbapDecoder(Stream(0, Transport.TCP, "client", sim.address), Direction.C2S)
            if tcp
            else None
        )
        self._pending: deque[ModbusPDU] = deque()
        self._worker: asyncio.Task[None] | None = None
        self._paused = False
        if tcp:
            # pymodbus drops a whole read longer than one ADU (264 bytes) unseen: here
            # every read is consumed at once and MbapDecoder bounds what it holds
            self.max_buffer_size = READ_LIMIT

    # ------------------------------------------------------------------ bytes in

    def callback_data(self, data: bytes, addr: tuple[Any, ...] | None = None) -> int:
        """Frame what arrived; queue every complete request; consume every byte."""
        if self._mbap is None:
            return self._rtu_data(data, addr)
        for item in self._mbap.feed(bytes(data), 0.0):
            if type(item) is not Frame:
                continue  # not an ADU: a server does not answer noise
            self.trace_packet(False, item.raw)
            pdu = self.server.decoder.decode(item.raw[7:])
            if pdu is not None:
                pdu.dev_id, pdu.transaction_id = item.unit, item.tid
                pdu = self.trace_pdu(False, pdu)  # the sim's hook: SimServer.admit
            else:
                tid = item.tid if item.tid is not None else 0  # MBAP frames carry one
                pdu = self.sim.admit(None, item.raw[7], item.unit, tid)
            if pdu is not None:
                self._pending.append(pdu)
        if self._pending:
            if self._worker is None or self._worker.done():
                self._worker = self.loop.create_task(self._answer_all())
            if len(self._pending) >= MAX_PENDING and not self._paused and self.transport:
                self._paused = True
                self.transport.pause_reading()  # type: ignore[attr-defined]
        return len(data)

    def _rtu_data(self, data: bytes, addr: tuple[Any, ...] | None) -> int:
        """pymodbus's RTU path; a request it cannot decode answered with its own code.

        pymodbus cannot frame a function code it does not know (it skips the bytes
        as garbage); what it holds is then a request when the CRC validates over
        all of it (a bus master sends one request and waits): it is answered too.
        """
        if len(data) >= 4 and self._memo.inner.lookupPduClass(data) is None and check_crc(data):
            self._refuse_rtu(data[1], data[0], addr)
            return len(data)
        try:
            used = TransactionManager.callback_data(self, data, addr)
        except ModbusIOException as exc:
            self._refuse_rtu(self._memo.last_fc, exc.dev_id or 0, addr)
            return len(data)
        if self.last_pdu:
            self.loop.call_soon(self.handle_later)
        return used

    def _refuse_rtu(self, fc: int, unit: int, addr: tuple[Any, ...] | None) -> None:
        """Answer an RTU request pymodbus could not take, unless it is a broadcast
        (unit 0: never answered) or for another device (:meth:`SimServer.admit`)."""
        answer = self.sim.admit(None, fc, unit, 0)
        if answer is not None and unit != 0:
            self.loop.create_task(self._answer(answer, addr))

    # ------------------------------------------------------------------ answers out

    async def _answer_all(self) -> None:
        """Answer the queued requests one after the other, in arrival order."""
        while self._pending and self.transport is not None:
            await self._answer(self._pending.popleft(), None)
            if self._paused and len(self._pending) < MAX_PENDING // 2 and self.transport:
                self._paused = False
                self.transport.resume_reading()  # type: ignore[attr-defined]
        self._pending.clear()

    async def _answer(self, request: Any, addr: tuple[Any, ...] | None) -> None:
        """Run one request (or refusal) against the datastore and send its answer."""
        from pymodbus.constants import ExcCodes

        try:
            response = await request.datastore_update(self.server.context, request.dev_id)
        except Exception:  # the robot's hook failed: the device failed, the server goes on
            response = ExceptionResponse(request.function_code, ExcCodes.DEVICE_FAILURE)
        if response is None or self.transport is None:
            return
        response.transaction_id = request.transaction_id
        response.dev_id = request.dev_id
        with contextlib.suppress(Exception):
            self.server_send(response, addr)


class SimTcpServer(ModbusTcpServer):
    """pymodbus's TCP server with :class:`SimRequestHandler` for each connection."""

    sim: SimServer

    def callback_new_connection(self) -> SimRequestHandler:
        return SimRequestHandler(self, self.sim, tcp=True)


class SimSerialServer(ModbusSerialServer):
    """pymodbus's serial server with :class:`SimRequestHandler` on the line."""

    sim: SimServer

    def callback_new_connection(self) -> SimRequestHandler:
        return SimRequestHandler(self, self.sim, tcp=False)
