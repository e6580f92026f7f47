"""Pairing of requests and responses into :class:`~mbmon.model.Transaction` steps.

Every frame yields exactly one transaction step; timeouts add one more each:

* a request yields ``PENDING`` (and is remembered, except an RTU broadcast);
* a response matched to its request yields ``ANSWERED`` or ``EXCEPTION`` with
  ``latency = response.ts - request.ts``; the response's PDU is decoded again
  with the request as context (so 01/02 bit lists are trimmed to the requested
  count);
* a response with nothing to match yields ``UNSOLICITED``;
* a request that gets no answer yields ``TIMEOUT`` from :meth:`Pairer.tick`,
  :meth:`Pairer.flush`, or when a later request makes the answer impossible
  (see below); its ``ts`` is when the answer was due (the request's time plus
  ``timeout``), or the time it was decided if that came first (a later request,
  the end of the input) -- never a later packet's time;
* a request the spec says is never answered (Diagnostics 04, Force Listen Only
  Mode, see :func:`expects_reply`) is never pending, like an RTU broadcast.

Matching rules, one :class:`Pairer` for all streams (keyed by ``stream.id``):

* MBAP transports (TCP, UDP): by (transaction id, unit id); the function code
  must agree too. A new request reusing a pending (tid, unit) replaces the old
  one, which times out.
* RTU transports (serial bus, RTU over TCP/UDP): by order. Only one request
  can be outstanding on a bus, so a new request times out the pending one. A
  response matches the pending request when unit and function code agree,
  else it is unsolicited (and the pending request stays). A broadcast request
  (unit 0) expects no response and is never pending.

Memory is bounded: at most ``max_pending`` requests wait per stream and at
most ``max_total`` over all streams; beyond either bound the oldest time out
(over all streams, the oldest eighth of the bound at once, so that a flood of
unanswered requests costs amortised O(log n) per request). Pure: no clocks,
``tick(now)`` is the only time source for timeouts.
"""

from __future__ import annotations

from mbmon.model import (
    RTU_TRANSPORTS,
    Direction,
    Frame,
    Kind,
    Pdu,
    Transaction,
    TxStatus,
    fast_constructor,
)
from mbmon.protocol.functions import PAIR_ALWAYS as _PAIR_ALWAYS
from mbmon.protocol.functions import PAIR_ON_COUNT as _PAIR_ON_COUNT
from mbmon.protocol.pdu import NO_REPLY_DIAGNOSTICS, decode_pdu

__all__ = ["DEFAULT_MAX_PENDING", "DEFAULT_MAX_TOTAL", "Pairer", "expects_reply"]

DEFAULT_MAX_PENDING = 10_000
"""Largest number of outstanding requests remembered per stream."""

DEFAULT_MAX_TOTAL = 100_000
"""Largest number of outstanding requests remembered over all streams."""

_Key = tuple[int, int]  # (tid, unit) for MBAP; (0, 0) for the one RTU slot

# Per frame: enum members as module constants (an attribute of an enum class costs
# about 70 ns, a global 10 ns) and constructors about twice as fast as the classes'.
_C2S, _S2C = Direction.C2S, Direction.S2C
_REQUEST, _EXCEPTION = Kind.REQUEST, Kind.EXCEPTION
_PENDING, _ANSWERED, _EXC = TxStatus.PENDING, TxStatus.ANSWERED, TxStatus.EXCEPTION
_UNSOLICITED = TxStatus.UNSOLICITED
_new_tx = fast_constructor(Transaction)
_new_frame = fast_constructor(Frame)


def expects_reply(req: Frame) -> bool:
    """Whether a server answers the request ``req``: not an RTU broadcast (unit 0 on
    an RTU transport) and not a Diagnostics sub-function the spec leaves unanswered
    (04, Force Listen Only Mode). Pairing holds only these; the pipeline too."""
    if req.unit == 0 and req.stream.transport in RTU_TRANSPORTS:
        return False
    pdu = req.pdu
    return pdu.fc != 0x08 or pdu.fields.get("sub_function") not in NO_REPLY_DIAGNOSTICS


class Pairer:
    """Pairs frames of all streams; owns the pending requests of every stream.

    ``timeout`` (seconds) is how long a request may wait for its response
    before :meth:`tick` reports it as ``TIMEOUT``. Requests are expected in
    roughly increasing time order per stream: :meth:`tick` checks them oldest
    first and stops at the first that has not expired.
    """

    __slots__ = ("_joined", "_pending", "_total", "max_pending", "max_total", "timeout")

    def __init__(
        self,
        timeout: float = 1.0,
        max_pending: int = DEFAULT_MAX_PENDING,
        max_total: int = DEFAULT_MAX_TOTAL,
    ) -> None:
        self.timeout = timeout
        self.max_pending = max(1, max_pending)
        self.max_total = max(1, max_total)
        # stream id -> pending requests in arrival order (dicts keep insertion order)
        self._pending: dict[int, dict[_Key, Frame]] = {}
        # how many requests _pending holds (kept by every writer of _pending)
        self._total = 0
        # stream id -> the stream whose requests its frames pair with (:meth:`join`)
        self._joined: dict[int, int] = {}

    def join(self, sid: int, into: int) -> None:
        """Frames of stream ``sid`` pair as if they were on stream ``into`` (a proxy's
        own answers to a client, on a stream of their own, answer the requests the
        client sent on its stream to the server)."""
        if sid != into:
            self._joined[sid] = self._joined.get(into, into)

    def part(self, sid: int) -> None:
        """Stream ``sid`` pairs on its own again (it ended)."""
        self._joined.pop(sid, None)

    @property
    def pending_count(self) -> int:
        """How many requests are waiting for a response, over all streams."""
        return self._total

    def feed(self, frame: Frame) -> list[Transaction]:
        """Pair one frame; return its step, preceded by any timeouts it causes."""
        direction = frame.direction
        if direction is _S2C or (direction is not _C2S and frame.pdu.kind is not _REQUEST):
            return [self._response(frame)]
        return self._request(frame)

    def tick(self, now: float) -> list[Transaction]:
        """Time out every request older than ``timeout`` at time ``now``."""
        out: list[Transaction] = []
        timeout = self.timeout
        limit = now - timeout
        for sid in list(self._pending):
            pend = self._pending[sid]
            while pend:
                key = next(iter(pend))
                req = pend[key]
                if req.ts > limit:
                    break
                del pend[key]
                self._total -= 1
                out.append(Transaction(min(req.ts + timeout, now), TxStatus.TIMEOUT, req, None))
            if not pend:
                del self._pending[sid]
        return out

    def next_deadline(self) -> float | None:
        """When the oldest pending request of any stream times out, or ``None``."""
        oldest = [next(iter(pend.values())).ts for pend in self._pending.values() if pend]
        return min(oldest) + self.timeout if oldest else None

    def flush(self, ts: float) -> list[Transaction]:
        """End of input: every pending request times out, at ``ts`` at the latest."""
        timeout = self.timeout
        out = [
            Transaction(min(req.ts + timeout, ts), TxStatus.TIMEOUT, req, None)
            for pend in self._pending.values()
            for req in pend.values()
        ]
        self._pending.clear()
        self._total = 0
        return out

    # ------------------------------------------------------------------ internals

    def _request(self, req: Frame) -> list[Transaction]:
        out: list[Transaction] = []
        sid = req.stream.id
        if self._joined:
            sid = self._joined.get(sid, sid)
        pend = self._pending.get(sid)
        if req.stream.transport in RTU_TRANSPORTS:
            if pend:
                out.extend(
                    Transaction(min(old.ts + self.timeout, req.ts), TxStatus.TIMEOUT, old, None)
                    for old in pend.values()
                )
                self._total -= len(pend)
                pend.clear()
            if req.unit != 0 and (req.pdu.fc != 0x08 or expects_reply(req)):
                if pend is None:
                    pend = self._pending[sid] = {}
                pend[(0, 0)] = req
                self._total += 1
        else:
            key = (req.tid or 0, req.unit)
            if pend is None:
                pend = self._pending[sid] = {}
            old = pend.pop(key, None)
            if old is not None:
                out.append(
                    Transaction(min(old.ts + self.timeout, req.ts), TxStatus.TIMEOUT, old, None)
                )
                self._total -= 1
            if req.pdu.fc != 0x08 or expects_reply(req):
                pend[key] = req
                self._total += 1
            while len(pend) > self.max_pending:
                oldest = next(iter(pend))
                out.append(Transaction(req.ts, TxStatus.TIMEOUT, pend.pop(oldest), None))
                self._total -= 1
        if pend is not None and not pend:
            del self._pending[sid]
        if self._total > self.max_total:
            self._evict(req.ts, out)
        out.append(_new_tx(req.ts, _PENDING, req, None, None))
        return out

    def _evict(self, ts: float, out: list[Transaction]) -> None:
        """Over ``max_total``: the oldest requests of all streams time out at ``ts``
        until an eighth of the bound is free again."""
        keep = self.max_total - max(1, self.max_total // 8)
        drop = self._total - keep
        if drop <= 0:
            return
        every = [
            (req.ts, n, sid, key)
            for sid, pend in self._pending.items()
            for n, (key, req) in enumerate(pend.items())
        ]
        every.sort()  # by time, then arrival order within a stream
        for _, _, sid, key in every[:drop]:
            pend = self._pending[sid]
            out.append(Transaction(ts, TxStatus.TIMEOUT, pend.pop(key), None))
            if not pend:
                del self._pending[sid]
        self._total -= drop

    def _response(self, resp: Frame) -> Transaction:
        sid = resp.stream.id
        if self._joined:
            sid = self._joined.get(sid, sid)
        pend = self._pending.get(sid)
        key = (0, 0) if resp.stream.transport in RTU_TRANSPORTS else (resp.tid or 0, resp.unit)
        req = pend.get(key) if pend is not None else None
        if pend is None or req is None or req.unit != resp.unit or req.pdu.fc != resp.pdu.fc:
            return _new_tx(resp.ts, _UNSOLICITED, None, resp, None)
        del pend[key]
        self._total -= 1
        if not pend:
            del self._pending[sid]
        pdu = resp.pdu
        if _needs_request(pdu, req.pdu):
            pdu = decode_pdu(pdu.raw, True, request=req.pdu)
            resp = _new_frame(
                resp.ts,
                resp.stream,
                resp.direction,
                resp.unit,
                resp.tid,
                pdu,
                resp.raw,
                resp.crc_ok,
            )
        status = _EXC if pdu.kind is _EXCEPTION else _ANSWERED
        return _new_tx(resp.ts, status, req, resp, resp.ts - req.ts)


def _needs_request(resp: Pdu, req: Pdu) -> bool:
    """Whether decoding ``resp`` with its request changes it (hot path: skip when not).

    Which codes need it is in the function-code table: bit reads are trimmed to
    the requested count (:data:`~mbmon.protocol.functions.PAIR_ALWAYS`); register
    reads are only checked against it, which matters when the byte count
    disagrees (:data:`~mbmon.protocol.functions.PAIR_ON_COUNT`); diagnostics and
    file records copy or compare fields of the request.
    """
    if resp.kind is _EXCEPTION:
        return False
    fc = resp.fc
    if fc in _PAIR_ON_COUNT:
        return req.count is not None and resp.byte_count != 2 * req.count
    return fc in _PAIR_ALWAYS
