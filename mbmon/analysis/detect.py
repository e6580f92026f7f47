"""Modbus on any TCP port, found by its structure (the dissector's port detection).

This module owns the decision whether a TCP connection on a port nobody named
carries Modbus: :class:`PortDetector` watches the connections the dissector
would otherwise drop as "not Modbus", keeps their first segments, and
promotes a connection only when its bytes corroborate each other:

* **Modbus/TCP (MBAP):** every byte either side sent so far parses as MBAP
  headers that chain (protocol id 0, a length of 2..254 that leads exactly to
  the next header; an unfinished last ADU may wait for its next segment), and
  one request is answered: an ADU from the client and a later ADU from the
  server with the same transaction id, unit id and function code (or that code
  with the exception bit), each of the length the function-code table gives
  for its code and direction (:func:`mbmon.protocol.pdu.pdu_length`; a code
  without a predictable length must decode without a spec violation).
* **RTU over TCP:** every byte of the client parses as RTU requests and every
  byte of the server as RTU responses, each frame of its predicted length with
  a valid CRC16, and one request is answered (same unit id, same function code
  or its exception).

One lucky header never promotes anything: a promotion needs two ADUs of two
directions agreeing in transaction id (MBAP), unit and function code, on top
of lengths that chain. A connection whose bytes break the structure is
rejected at once and costs a dictionary lookup per packet afterwards.

Once a connection is promoted, its server endpoint (address and port) is
known Modbus for the rest of the run: later connections to it are streams at
once. The segments held while deciding are handed back to the dissector,
which replays them through TCP reassembly, so a promoted stream loses nothing
(its CONNECT, its first request and answer keep their own capture times).

Bounded: at most :data:`MAX_CANDIDATES` undecided connections (the oldest is
rejected when more come), each holding at most :data:`MAX_SEGMENTS` segments
and :data:`MAX_BYTES` payload bytes (a connection that has not proved itself
by then is rejected), at most :data:`MAX_REJECTED` rejected connections
remembered and :data:`MAX_SERVERS` promoted endpoints.

Limits, by design: only TCP (not UDP); a connection whose first captured
payload starts inside an ADU (the capture began mid-ADU) or that loses a
segment before it proved itself is not promoted (a later connection to the
same server is). Pure: no I/O, no clocks.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

from mbmon.model import Transport
from mbmon.protocol.crc import crc_ok_at
from mbmon.protocol.functions import NEED_MORE
from mbmon.protocol.pdu import decode_pdu, pdu_length

__all__ = [
    "MAX_BYTES",
    "MAX_CANDIDATES",
    "MAX_REJECTED",
    "MAX_SEGMENTS",
    "MAX_SERVERS",
    "Found",
    "PortDetector",
    "Promotion",
    "Segment",
]

#: Undecided connections watched at most (the least recently started is rejected).
MAX_CANDIDATES = 1024
#: Segments held per undecided connection before it is rejected.
MAX_SEGMENTS = 64
#: Payload bytes held per undecided connection before it is rejected.
MAX_BYTES = 16384
#: Rejected connections remembered (the oldest are forgotten: watched again).
MAX_REJECTED = 65536
#: Promoted server endpoints at most.
MAX_SERVERS = 4096

_SYN = 0x02
_ACK = 0x10
_RST = 0x04
_MASK = 0xFFFFFFFF
_HALF = 0x80000000

Key = tuple[bytes, int, int]  # (source + destination address, source port, destination port)
#: One held segment, as the dissector saw it: (ts, key, seq, ack, flags, payload).
Segment = tuple[float, Key, int, int, int, bytes]


def _reverse(key: Key) -> Key:
    addrs, sport, dport = key
    half = len(addrs) // 2
    return (addrs[half:] + addrs[:half], dport, sport)


def _endpoint(key: Key, source: bool) -> tuple[bytes, int]:
    addrs, sport, dport = key
    half = len(addrs) // 2
    return (addrs[:half], sport) if source else (addrs[half:], dport)


@dataclass(frozen=True, slots=True)
class Found:
    """A server endpoint promoted by structure: its transport, address (raw
    bytes, 4 or 16) and port."""

    transport: Transport
    address: bytes
    port: int


@dataclass(frozen=True, slots=True)
class Promotion:
    """A connection proved to be Modbus: the segments held so far (the current
    one last), in capture order, for the dissector to replay."""

    segments: list[Segment]
    found: Found


class _Side:
    """One direction of an undecided connection: its bytes in sequence order and
    when they arrived."""

    __slots__ = ("buf", "marks", "nxt")

    def __init__(self) -> None:
        self.nxt: int | None = None
        self.buf = bytearray()
        self.marks: list[tuple[int, float]] = []  # (bytes held after a segment, its time)

    def time_of(self, end: int) -> float:
        """Capture time of the segment that brought byte ``end - 1``."""
        for length, ts in self.marks:
            if length >= end:
                return ts
        return self.marks[-1][1]


class _Candidate:
    """An undecided connection: its held segments and both directions' bytes.

    ``a`` is the direction of the connection's first key (the first packet's
    sender), ``b`` the other; ``syn_from_a`` is True/False once a bare SYN
    named the client, else None."""

    __slots__ = ("a", "b", "first_key", "held", "mbap", "rtu_a", "rtu_b", "segments", "syn_from_a")

    def __init__(self, key: Key) -> None:
        self.first_key = key
        self.a = _Side()
        self.b = _Side()
        self.segments: list[Segment] = []
        self.held = 0
        self.syn_from_a: bool | None = None
        # the hypotheses still open: MBAP, RTU with a as client, RTU with b as client
        self.mbap = True
        self.rtu_a = True
        self.rtu_b = True


class PortDetector:
    """Which TCP connections on unnamed ports carry Modbus (module docstring).

    The dissector calls :meth:`serves` for a packet of a connection it does not
    know, then :meth:`segment`; :meth:`role` tells it the roles of a new
    connection to a promoted endpoint; :meth:`found` lists what was promoted.
    """

    def __init__(self) -> None:
        self._candidates: dict[Key, _Candidate] = {}  # both keys of each candidate
        self._order: OrderedDict[_Candidate, None] = OrderedDict()
        self._rejected: OrderedDict[Key, None] = OrderedDict()  # first key and reverse
        # promoted server endpoints -> transport; and how many streams each gave
        self._servers: dict[tuple[bytes, int], Transport] = {}
        self.streams: dict[tuple[bytes, int], int] = {}
        self.rejected = 0  # connections rejected
        self.promoted = 0  # connections promoted by their own bytes

    # ------------------------------------------------------------------ queries

    def role(self, key: Key) -> tuple[bool, Transport] | None:
        """For a new connection whose first packet has ``key``: ``(whether its
        sender is the client, transport)`` when one end is a promoted server
        endpoint, else ``None``."""
        servers = self._servers
        if not servers:
            return None
        dst = _endpoint(key, False)
        transport = servers.get(dst)
        if transport is not None:
            self.streams[dst] = self.streams.get(dst, 0) + 1
            return True, transport
        src = _endpoint(key, True)
        transport = servers.get(src)
        if transport is not None:
            self.streams[src] = self.streams.get(src, 0) + 1
            return False, transport
        return None

    def serves(self, key: Key) -> bool:
        """Whether one end of ``key`` is a promoted server endpoint."""
        servers = self._servers
        return bool(servers) and (
            _endpoint(key, False) in servers or _endpoint(key, True) in servers
        )

    def found(self) -> list[tuple[str, int, bytes, int]]:
        """Every promoted endpoint: ``(transport value, port, address bytes,
        streams)``, in the order they were found."""
        return [
            (transport.value, port, address, self.streams.get((address, port), 0))
            for (address, port), transport in self._servers.items()
        ]

    # ------------------------------------------------------------------ input

    def segment(
        self, ts: float, key: Key, seq: int, ack: int, flags: int, payload: bytes
    ) -> Promotion | bool:
        """One TCP segment of a connection on no Modbus port (and of no promoted
        endpoint). Returns a :class:`Promotion` when this segment proved the
        connection Modbus, ``True`` while it is undecided (the segment is held),
        ``False`` when the connection is not Modbus."""
        if key in self._rejected:
            return False
        cand = self._candidates.get(key)
        if cand is None:
            if not payload and flags & (_SYN | _ACK) != _SYN:
                return False  # an ACK, FIN or RST of something never seen: nothing to watch
            cand = self._new(key)
        from_a = key == cand.first_key
        cand.segments.append((ts, key, seq, ack, flags, payload))
        side = cand.a if from_a else cand.b
        if flags & _SYN:
            if flags & (_SYN | _ACK) == _SYN:
                cand.syn_from_a = from_a
            if side.nxt is None:
                side.nxt = (seq + 1) & _MASK
        if flags & _RST:
            self._reject(cand)
            return False
        if payload:
            if side.nxt is None:
                side.nxt = seq
            ahead = (seq - side.nxt) & _MASK
            if ahead:
                end = (seq + len(payload) - side.nxt) & _MASK
                if ahead & _HALF and not (end and end < _HALF):
                    return self._held(cand)  # a retransmission of bytes already held
                if ahead & _HALF:  # overlaps old and new bytes: keep the new ones
                    payload = payload[len(payload) - end :]
                else:  # a hole: the structure cannot be followed
                    self._reject(cand)
                    return False
            side.buf += payload
            side.nxt = (side.nxt + len(payload)) & _MASK
            side.marks.append((len(side.buf), ts))
            cand.held += len(payload)
            found = self._judge(cand)
            if found is False:
                self._reject(cand)
                return False
            if found is not None:
                return self._promote(cand, found)
        return self._held(cand)

    # ------------------------------------------------------------------ internals

    def _new(self, key: Key) -> _Candidate:
        if len(self._order) >= MAX_CANDIDATES:
            self._reject(next(iter(self._order)))
        cand = _Candidate(key)
        self._candidates[key] = cand
        self._candidates[_reverse(key)] = cand
        self._order[cand] = None
        return cand

    def _held(self, cand: _Candidate) -> bool:
        if len(cand.segments) > MAX_SEGMENTS or cand.held > MAX_BYTES:
            self._reject(cand)
            return False
        return True

    def _forget(self, cand: _Candidate) -> None:
        key = cand.first_key
        self._candidates.pop(key, None)
        self._candidates.pop(_reverse(key), None)
        self._order.pop(cand, None)

    def _reject(self, cand: _Candidate) -> None:
        self._forget(cand)
        self.rejected += 1
        rejected = self._rejected
        while len(rejected) >= MAX_REJECTED:
            rejected.popitem(last=False)
        rejected[cand.first_key] = None
        rejected[_reverse(cand.first_key)] = None

    def _promote(self, cand: _Candidate, found: tuple[Transport, bool]) -> Promotion | bool:
        transport, client_is_a = found
        self._forget(cand)
        server = _endpoint(cand.first_key, not client_is_a)
        if server not in self._servers and len(self._servers) >= MAX_SERVERS:
            return False
        self._servers[server] = transport
        self.promoted += 1
        segments = cand.segments
        # other undecided connections to the same server are Modbus too: their held
        # segments are replayed with this one's, in capture order
        siblings = [
            other
            for other in list(self._order)
            if server in (_endpoint(other.first_key, False), _endpoint(other.first_key, True))
        ]
        if siblings:
            for other in siblings:
                self._forget(other)
                segments = segments + other.segments
            segments.sort(key=lambda segment: segment[0])  # stable: each connection's order
        return Promotion(segments, Found(transport, server[0], server[1]))

    def _judge(self, cand: _Candidate) -> tuple[Transport, bool] | Literal[False] | None:
        """The verdict on a candidate's bytes so far: ``(transport, whether side a
        is the client)`` when proved, ``False`` when no hypothesis is left,
        ``None`` while undecided."""
        a, b = cand.a, cand.b
        if cand.mbap:
            adus_a, adus_b = _mbap_adus(a.buf), _mbap_adus(b.buf)
            if adus_a is None or adus_b is None:
                cand.mbap = False
            else:
                for client_is_a in _orientations(cand.syn_from_a):
                    requests, responses = (adus_a, adus_b) if client_is_a else (adus_b, adus_a)
                    cside, sside = (a, b) if client_is_a else (b, a)
                    if _mbap_answered(requests, responses, cside, sside):
                        return Transport.TCP, client_is_a
        for client_is_a in _orientations(cand.syn_from_a):
            if not (cand.rtu_a if client_is_a else cand.rtu_b):
                continue
            cside, sside = (a, b) if client_is_a else (b, a)
            asked = _rtu_frames(cside.buf, response=False)
            answers = _rtu_frames(sside.buf, response=True)
            if asked is None or answers is None:
                if client_is_a:
                    cand.rtu_a = False
                else:
                    cand.rtu_b = False
                continue
            if _rtu_answered(asked, answers, cside, sside):
                return Transport.RTU_OVER_TCP, client_is_a
        if cand.syn_from_a is not None:  # the SYN fixed the roles: the other one is out
            if cand.syn_from_a:
                cand.rtu_b = False
            else:
                cand.rtu_a = False
        if not (cand.mbap or cand.rtu_a or cand.rtu_b):
            return False
        return None


def _orientations(syn_from_a: bool | None) -> tuple[bool, ...]:
    return (True, False) if syn_from_a is None else (syn_from_a,)


# (transaction id, unit, PDU, end offset in the side's bytes)
_Adu = tuple[int, int, bytes, int]


def _mbap_adus(buf: bytearray) -> list[_Adu] | None:
    """The complete MBAP ADUs at the start of ``buf`` (an unfinished one at the
    end waits), or ``None`` when a header breaks the chain."""
    adus: list[_Adu] = []
    pos, size = 0, len(buf)
    while size - pos >= 6:
        if buf[pos + 2] or buf[pos + 3]:
            return None  # protocol id not 0
        length = (buf[pos + 4] << 8) | buf[pos + 5]
        if not 2 <= length <= 254:
            return None
        end = pos + 6 + length
        if end > size:
            break
        adus.append(((buf[pos] << 8) | buf[pos + 1], buf[pos + 6], bytes(buf[pos + 7 : end]), end))
        pos = end
    return adus


def _pdu_fits(pdu: bytes, response: bool) -> bool:
    """Whether ``pdu`` has the length the function-code table gives for its code
    (a code without a predictable length: decodes without a spec violation)."""
    fc = pdu[0]
    if fc == 0 or (fc & 0x80 and not response):
        return False
    if fc & 0x80:
        return len(pdu) == 2 and pdu[1] != 0
    expected = pdu_length(pdu, response)
    if expected is None:
        return decode_pdu(pdu, response).malformed is None
    return expected == len(pdu)


def _mbap_answered(requests: list[_Adu], responses: list[_Adu], cside: _Side, sside: _Side) -> bool:
    """One request answered by a later response echoing its transaction id,
    unit and function code, both of their table lengths."""
    if not requests or not responses:
        return False
    asked: dict[tuple[int, int, int], float] = {}
    for tid, unit, pdu, end in requests:
        if _pdu_fits(pdu, False):
            asked.setdefault((tid, unit, pdu[0]), cside.time_of(end))
    for tid, unit, pdu, end in responses:
        when = asked.get((tid, unit, pdu[0] & 0x7F))
        if when is not None and when <= sside.time_of(end) and _pdu_fits(pdu, True):
            return True
    return False


# (unit, function code, end offset)
_Rtu = tuple[int, int, int]


def _rtu_frames(buf: bytearray, *, response: bool) -> list[_Rtu] | None:
    """The RTU frames at the start of ``buf`` for one direction, each of its
    predicted length with a valid CRC (a code without a predictable length: the
    rest of the bytes, when their CRC is valid); ``None`` when the bytes break
    that. An unfinished frame at the end waits."""
    frames: list[_Rtu] = []
    pos, size = 0, len(buf)
    view = memoryview(buf)
    try:
        while size - pos >= 4:
            unit, fc = buf[pos], buf[pos + 1]
            if fc == 0 or (fc & 0x80 and not response) or (unit > 247 and not response):
                return None
            n = pdu_length(view[pos + 1 :], response)
            if n == NEED_MORE:
                break
            if n is None:
                end = size
                if end - pos > 256:
                    return None
                if not crc_ok_at(buf, pos, end):
                    break  # the rest of the frame may be on its way
            else:
                end = pos + 1 + n + 2
                if end > size:
                    break
                if end - pos > 256 or not crc_ok_at(buf, pos, end):
                    return None
            frames.append((unit, fc, end))
            pos = end
    finally:
        view.release()
    if size - pos > 256:
        return None
    return frames


def _rtu_answered(requests: list[_Rtu], responses: list[_Rtu], cside: _Side, sside: _Side) -> bool:
    """One request answered by a later response of the same unit and code."""
    asked: dict[tuple[int, int], float] = {}
    for unit, fc, end in requests:
        if unit:  # a broadcast is never answered
            asked.setdefault((unit, fc), cside.time_of(end))
    for unit, fc, end in responses:
        when = asked.get((unit, fc & 0x7F))
        if when is not None and when <= sside.time_of(end):
            return True
    return False
