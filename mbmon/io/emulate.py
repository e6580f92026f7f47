"""``replay --serve``: a recorded server emulated from its log.

What this module owns:

- :class:`RegisterImage` (pure): the recorded server's data, per unit id, built
  from every exchange of the log (:func:`mbmon.io.exchanges.recorded_exchanges`)
  and changed by the new client's writes. :meth:`RegisterImage.answer` turns a
  request PDU into the response PDU the recorded server would give, or the
  miss exception, and keeps the list of misses.
- :class:`EmulatorServer`: a Modbus/TCP server (asyncio, loopback unless told)
  that frames requests with mbmon's own MBAP decoder and answers each from the
  image with the request's transaction and unit id.

What the image learns from an exchange answered normally (a request the server
answered with an exception, or never answered, changes nothing):

- read responses (01 02 03 04, the read part of 17): their values at the
  request's addresses, in the coil, discrete-input, holding- or input-register
  table; the last value seen wins;
- writes (05 06 0F 10 16, the write part of 17): the written values (16: the
  mask applied to the known value);
- every other function code (07 08 0B 0C 11 14 15 18 2B, user codes): the
  exact response to the exact request bytes.

How a request is answered: with ``state="follow"``, a read (01 02 03 04)
whose exact bytes the log holds gets the recorded answers to that request in
the recorded order, one per repetition, and the last one once they run out
(values the new client wrote itself stay what it wrote); so a client that
repeats the recorded session, polling IR524 until the robot is Idle, sees it
Running and then Idle as the recording did. A request whose key (unit,
function, address, count) the recorded server only ever refused gets that
recorded exception; a read whose every address is known gets the values; a
write whose every address is known is applied and answered as the spec says;
any other request is a miss, answered with ``miss_exception`` (02 Illegal
Data Address by default) and counted in :attr:`RegisterImage.misses`.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from mbmon.io.exchanges import Exchange
from mbmon.model import Direction, Frame, Kind, Pdu, Stream, Transport
from mbmon.protocol.functions import FUNCTIONS, SHAPE, mask_write
from mbmon.protocol.pdu import (
    FUNCTION_NAMES,
    encode_exception,
    encode_read_response,
    encode_write_multiple_response,
    table_of,
)

__all__ = ["STATES", "TABLE_NAMES", "EmulatorServer", "Miss", "RegisterImage", "ranges"]

#: table -> the words a summary uses
TABLE_NAMES = {
    "coil": "coils",
    "discrete_input": "discrete inputs",
    "holding_register": "holding registers",
    "input_register": "input registers",
}
_EXC_ILLEGAL_VALUE = 0x03
#: the shapes (:data:`mbmon.protocol.functions.SHAPE`) of the reads whose recorded
#: answers ``state="follow"`` gives again in the recorded order
_FOLLOWED = ("read",)
#: the shapes whose answer carries values the image learns
_READ_SHAPES = ("read", "read_write")


def _bit_read(fc: int) -> bool:
    """Whether ``fc`` reads bits (its answer is padded to whole bytes)."""
    spec = FUNCTIONS.get(fc)
    return spec is not None and spec.bits and spec.read


#: the values of :attr:`RegisterImage.state`
STATES = ("follow", "first", "last")
#: kinds of missed request listed one by one; beyond, they are only counted (a client
#: sweeping the address space must not grow the list without bound)
MAX_MISS_KINDS = 4096

Key = tuple[int, int, int | None, int | None, int | bytes | None, int | None]


@dataclass(slots=True)
class Miss:
    """Requests of one kind the image could not answer: how often, which addresses were unknown."""

    unit: int
    fc: int
    address: int | None
    count: int | None
    table: str | None
    times: int = 0
    unknown: tuple[tuple[int, int], ...] = ()

    def describe(self) -> str:
        """One line of the end-of-run summary."""
        name = FUNCTION_NAMES.get(self.fc, "function")
        what = f"unit {self.unit}, {self.fc:02X} {name}"
        if self.address is not None and self.count is not None and self.table is not None:
            last = self.address + max(self.count, 1) - 1
            what += f", {TABLE_NAMES[self.table]} {_span(self.address, last)}"
            unknown = ", ".join(_span(a, b) for a, b in self.unknown)
            if unknown and self.unknown != ((self.address, last),):
                what += f" (never seen: {unknown})"
        else:
            what += " (this request never seen)"
        times = "once" if self.times == 1 else f"{self.times} times"
        return f"{what}: {times}"


def _span(a: int, b: int) -> str:
    return str(a) if a == b else f"{a}-{b}"


def ranges(addresses: Iterable[int]) -> tuple[tuple[int, int], ...]:
    """Addresses as sorted inclusive runs: ``[1, 2, 3, 7]`` -> ``((1, 3), (7, 7))``."""
    out: list[list[int]] = []
    for a in sorted(set(addresses)):
        if out and a == out[-1][1] + 1:
            out[-1][1] = a
        else:
            out.append([a, a])
    return tuple((a, b) for a, b in out)


@dataclass(slots=True)
class RegisterImage:
    """The data of a recorded server, per unit id; see the module docstring.

    ``tables[(unit, table)]`` maps address -> value (registers 0..65535, bits 0/1).
    """

    miss_exception: int = 0x02
    #: ``"first"``: each address holds the first value the log shows for it (the server
    #: as the recording found it); ``"last"``: the last one (as the recording left it);
    #: ``"follow"``: as ``"first"``, and a repeated recorded read gets the recorded
    #: answers in their order (the server as the recording went; module docstring)
    state: str = "first"
    tables: dict[tuple[int, str], dict[int, int]] = field(default_factory=dict)
    #: (unit, request PDU) -> response PDU, for the codes that address no table
    verbatim: dict[tuple[int, bytes], bytes] = field(default_factory=dict)
    #: request keys the recorded server refused every time, with its exception code
    refused: dict[Key, int] = field(default_factory=dict)
    misses: dict[Key, Miss] = field(default_factory=dict)
    #: missed requests of kinds past :data:`MAX_MISS_KINDS`
    misses_unlisted: int = 0
    learned: int = 0
    answered: int = 0
    #: ``state="follow"``: (unit, read request PDU) -> its recorded answers not yet given
    script: dict[tuple[int, bytes], deque[Pdu]] = field(default_factory=dict)
    _accepted: set[Key] = field(default_factory=set)
    #: ``state="follow"``: addresses the new client wrote, per (unit, table)
    _written: dict[tuple[int, str], set[int]] = field(default_factory=dict)

    # ------------------------------------------------------------------ building

    @classmethod
    def from_exchanges(
        cls, exchanges: Iterable[Exchange], miss_exception: int = 0x02, state: str = "first"
    ) -> RegisterImage:
        """The image built from every exchange of a log, in order."""
        if state not in STATES:
            raise ValueError(f"state must be one of {', '.join(STATES)}, not {state!r}")
        image = cls(miss_exception, state)
        for ex in exchanges:
            image.learn(ex)
        return image

    def learn(self, ex: Exchange) -> None:
        """Take what one recorded exchange says about the server's data."""
        response = ex.response
        if response is None:
            return
        request = ex.request
        key = _key(ex.unit, request)
        if self.state == "follow" and SHAPE.get(request.fc) in _FOLLOWED and not request.malformed:
            self.script.setdefault((ex.unit, request.raw), deque()).append(response)
        if response.kind is Kind.EXCEPTION:
            if key not in self._accepted and response.exception_code is not None:
                self.refused[key] = response.exception_code
            return
        self._accepted.add(key)
        self.refused.pop(key, None)
        self.learned += 1
        fc = request.fc
        if table_of(fc) is None:
            self.verbatim[(ex.unit, request.raw)] = response.raw
            return
        self._apply_write(ex.unit, request, learning=True)
        if SHAPE.get(fc) in _READ_SHAPES and request.address is not None:
            values = response.values
            if values is None:
                return
            if _bit_read(fc) and request.count is not None:
                values = values[: request.count]  # bits past the count are padding
            table = self._table(ex.unit, table_of(fc) or "")
            keep = self.state != "last"
            for i, v in enumerate(values):
                if not keep or request.address + i not in table:
                    table[request.address + i] = v

    def _table(self, unit: int, table: str) -> dict[int, int]:
        found = self.tables.get((unit, table))
        if found is None:
            found = self.tables[(unit, table)] = {}
        return found

    # ------------------------------------------------------------------ answering

    @property
    def units(self) -> list[int]:
        """Unit ids the image knows anything about."""
        found = {u for u, _t in self.tables} | {u for u, _r in self.verbatim}
        return sorted(found | {k[0] for k in self.refused})

    def answer(self, unit: int, request: Pdu) -> bytes:
        """The response PDU for ``request`` to ``unit``; writes change the image."""
        key = _key(unit, request)
        fc = request.fc
        shape = SHAPE.get(fc)
        if self.state == "follow" and shape in _FOLLOWED:
            queue = self.script.get((unit, request.raw))
            if queue:
                return self._follow(unit, request, queue)
        if key in self.refused:
            self.answered += 1
            return encode_exception(fc, self.refused[key])
        table = table_of(fc)
        if table is None:
            found = self.verbatim.get((unit, request.raw))
            if found is None:
                return self._miss(key, unit, request, None, ())
            self.answered += 1
            return found
        if request.malformed or request.raw[0] & 0x80:
            self.answered += 1
            return encode_exception(fc, _EXC_ILLEGAL_VALUE)
        unknown = self._unknown_writes(unit, request)
        read_table: dict[int, int] = {}
        if shape in _READ_SHAPES:
            read_table = self.tables.get((unit, table), {})
            assert request.address is not None and request.count is not None  # not malformed
            wrote = set()
            if shape == "read_write":  # the write happens first: what it writes is known afterwards
                wa, wc = request.fields.get("write_address"), request.fields.get("write_count")
                if isinstance(wa, int) and isinstance(wc, int):
                    wrote = set(range(wa, wa + wc))
            unknown += [
                a
                for a in range(request.address, request.address + request.count)
                if a not in read_table and a not in wrote
            ]
        if unknown:
            return self._miss(key, unit, request, table, unknown)
        self._apply_write(unit, request, learning=False)
        if self.state == "follow":
            self._mark_written(unit, request)
        self.answered += 1
        if shape == "write_single" or shape == "mask_write":
            return request.raw  # the spec's echo
        if shape == "write_multiple":
            assert request.address is not None and request.count is not None
            return encode_write_multiple_response(fc, request.address, request.count)
        assert request.address is not None and request.count is not None
        read_table = self.tables.get((unit, table), {})
        values = [read_table[a] for a in range(request.address, request.address + request.count)]
        return encode_read_response(fc, values, request.count)

    def _follow(self, unit: int, request: Pdu, queue: deque[Pdu]) -> bytes:
        """The next recorded answer to a repeated read (the last one stays); the image
        takes its values, except where the new client wrote (there its values win)."""
        recorded = queue.popleft() if len(queue) > 1 else queue[0]
        self.answered += 1
        fc, address, count = request.fc, request.address, request.count
        name = table_of(fc)
        if recorded.kind is Kind.EXCEPTION or recorded.values is None or name is None:
            return recorded.raw
        if address is None or count is None:
            return recorded.raw
        bits = _bit_read(fc)
        values = list(recorded.values[:count] if bits else recorded.values)
        if bits and len(values) < count:
            return recorded.raw  # a short answer: given as it was, teaches nothing
        table = self._table(unit, name)
        written = self._written.get((unit, name), set())
        changed = False
        for i, v in enumerate(values):
            a = address + i
            if a in written and a in table:
                changed |= table[a] != v
                values[i] = table[a]
            else:
                table[a] = v
        return encode_read_response(fc, values, count) if changed else recorded.raw

    def _mark_written(self, unit: int, request: Pdu) -> None:
        """Remember the addresses a write of the new client set (``state="follow"``)."""
        if SHAPE.get(request.fc) == "mask_write":
            if request.address is not None:
                self._written.setdefault((unit, table_of(request.fc) or ""), set()).add(
                    request.address
                )
            return
        parts = self._write_parts(request)
        if parts is None:
            return
        name, address, values = parts
        self._written.setdefault((unit, name), set()).update(range(address, address + len(values)))

    def _miss(
        self, key: Key, unit: int, request: Pdu, table: str | None, unknown: Iterable[int]
    ) -> bytes:
        miss = self.misses.get(key)
        if miss is None and len(self.misses) >= MAX_MISS_KINDS:
            self.misses_unlisted += 1
            return encode_exception(request.fc, self.miss_exception)
        if miss is None:
            miss = Miss(unit, request.fc, request.address, request.count, table)
            self.misses[key] = miss
        miss.times += 1
        miss.unknown = ranges([*(a for r in miss.unknown for a in range(r[0], r[1] + 1)), *unknown])
        return encode_exception(request.fc, self.miss_exception)

    def miss_report(self) -> list[str]:
        """The misses, one line each, by unit, function code and address."""
        order = sorted(
            self.misses.values(), key=lambda m: (m.unit, m.fc, m.address or -1, m.count or 0)
        )
        lines = [m.describe() for m in order]
        if self.misses_unlisted:
            lines.append(f"{self.misses_unlisted} more requests of other kinds")
        return lines

    @property
    def missed(self) -> int:
        """How many requests were answered with the miss exception."""
        return sum(m.times for m in self.misses.values()) + self.misses_unlisted

    # ------------------------------------------------------------------ writes

    def _write_parts(self, request: Pdu) -> tuple[str, int, list[int | None]] | None:
        """(table, address, new values) of a write request; ``None`` in the list for a
        value that depends on an unknown one (16 with a mask that keeps bits)."""
        shape = SHAPE.get(request.fc)
        table = table_of(request.fc)
        if table is None:
            return None
        if shape == "write_single" or shape == "write_multiple":
            if request.address is None or request.values is None:
                return None
            return table, request.address, list(request.values)
        if shape == "read_write":
            wa, wv = request.fields.get("write_address"), request.fields.get("write_values")
            if not isinstance(wa, int) or wv is None:
                return None
            return table, wa, list(wv)
        return None

    def _unknown_writes(self, unit: int, request: Pdu) -> list[int]:
        """Addresses a write request touches that the image has never seen."""
        if SHAPE.get(request.fc) == "mask_write":
            a = request.address
            known = self.tables.get((unit, table_of(request.fc) or ""), {})
            return [] if a is None or a in known else [a]
        parts = self._write_parts(request)
        if parts is None:
            return []
        table, address, values = parts
        known = self.tables.get((unit, table), {})
        return [a for a in range(address, address + len(values)) if a not in known]

    def _apply_write(self, unit: int, request: Pdu, *, learning: bool) -> None:
        """Put a write's values in the image.

        A write the log shows (``learning``) makes addresses known; with ``state
        "first"`` it never replaces a value already known. A write of the new client
        changes known addresses only (the caller has checked they are all known).
        """
        keep = learning and self.state != "last"
        if SHAPE.get(request.fc) == "mask_write":
            a = request.address
            and_mask, or_mask = request.fields.get("and_mask"), request.fields.get("or_mask")
            if a is None or not isinstance(and_mask, int) or not isinstance(or_mask, int):
                return
            table = self._table(unit, table_of(request.fc) or "")
            current = table.get(a)
            if keep and current is not None:
                return
            if current is None and and_mask != 0:
                return  # the result keeps bits nobody has seen
            table[a] = mask_write(current or 0, and_mask, or_mask)
            return
        parts = self._write_parts(request)
        if parts is None:
            return
        name, address, values = parts
        table = self._table(unit, name)
        for i, v in enumerate(values):
            known = address + i in table
            if v is not None and (known if not learning else not (keep and known)):
                table[address + i] = v


def _key(unit: int, pdu: Pdu) -> Key:
    """What makes two requests "the same request" for refusals and misses."""
    if table_of(pdu.fc) is None:
        return (unit, pdu.fc, None, None, pdu.raw, None)
    wa, wc = pdu.fields.get("write_address"), pdu.fields.get("write_count")
    return (
        unit,
        pdu.fc,
        pdu.address,
        pdu.count,
        wa if isinstance(wa, int) else None,
        wc if isinstance(wc, int) else None,
    )


# --------------------------------------------------------------------------- the server


class EmulatorServer:
    """A Modbus/TCP server answering from a :class:`RegisterImage`.

    ``start()`` runs it in a background thread and returns ``(host, port)``
    (port 0 picks a free one); ``stop()`` ends it. ``await serve(stop_event)``
    runs it in the caller's loop. ``on_request(unit, request, response)`` sees
    every answered request (PDU bytes). Bytes that are not MBAP are dropped, as
    the MBAP decoder finds them; the connection stays open.
    """

    def __init__(
        self,
        image: RegisterImage,
        host: str = "127.0.0.1",
        port: int = 0,
        on_request: Callable[[int, bytes, bytes], None] | None = None,
    ) -> None:
        self.image = image
        self.host, self.port = host, port
        self.on_request = on_request
        self.connections = 0
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._clients: dict[asyncio.StreamWriter, asyncio.Task[None] | None] = {}

    async def serve(
        self, stop: asyncio.Event, on_ready: Callable[[str, int], None] | None = None
    ) -> None:
        """Listen until ``stop`` is set; ``on_ready(host, port)`` once listening."""
        server = await asyncio.start_server(self._client, self.host, self.port)
        sock = server.sockets[0].getsockname()
        self.host, self.port = str(sock[0]), int(sock[1])
        if on_ready is not None:
            on_ready(self.host, self.port)
        try:
            async with server:
                await stop.wait()
        finally:
            server.close()
            # close the clients ourselves: their handlers end on EOF, none is cancelled
            tasks = [t for t in self._clients.values() if t is not None]
            for writer in list(self._clients):
                writer.close()
            if tasks:
                await asyncio.wait(tasks, timeout=2.0)
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 1.0)

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        from mbmon.protocol.mbap import MbapDecoder, encode_adu

        self.connections += 1
        self._clients[writer] = asyncio.current_task()  # type: ignore[assignment]
        peer = writer.get_extra_info("peername") or ("?", 0)
        stream = Stream(self.connections, Transport.TCP, f"{peer[0]}:{peer[1]}",
                        f"{self.host}:{self.port}")  # fmt: skip
        decoder = MbapDecoder(stream, Direction.C2S)
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    break
                out = bytearray()
                for item in decoder.feed(data, 0.0):
                    if not isinstance(item, Frame) or item.tid is None:
                        continue  # noise: nothing a server could answer
                    response = self.image.answer(item.unit, item.pdu)
                    if self.on_request is not None:
                        self.on_request(item.unit, item.pdu.raw, response)
                    out += encode_adu(item.tid, item.unit, response)
                if out:
                    writer.write(bytes(out))
                    await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            self._clients.pop(writer, None)
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    def start(self, timeout: float = 10.0) -> tuple[str, int]:
        """Serve in a background thread; the address it listens on."""
        self._thread = threading.Thread(target=self._run, name="mbmon-emulator", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout) or self._error is not None:
            raise RuntimeError(f"emulator did not start: {self._error}")
        return self.host, self.port

    def _run(self) -> None:
        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            await self.serve(self._stop, lambda _h, _p: self._ready.set())

        try:
            asyncio.run(main())
        except BaseException as exc:  # reported by start()
            self._error = exc
            self._ready.set()

    def stop(self, timeout: float = 10.0) -> None:
        """End the background server and wait for its thread."""
        if self._loop is not None and self._stop is not None:
            with contextlib.suppress(RuntimeError):
                self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(timeout)

    def __enter__(self) -> EmulatorServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
