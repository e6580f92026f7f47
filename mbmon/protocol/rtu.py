"""Modbus RTU stream decoder: one serial byte stream (both directions) -> frames.

Framing is length prediction + CRC (DESIGN rules 2 and 3), never timing:

* At the current offset the first byte is the unit id and the second the
  function code. :func:`mbmon.protocol.pdu.pdu_length` predicts the PDU length
  of the request and of the response reading (an exception response is a
  2-byte PDU); each candidate ADU is ``1 + PDU + 2`` bytes and is confirmed by
  its CRC16.
* The pending request decides which reading comes first: when the master asked
  unit U with function F, a frame from U with F (or F | 0x80) is taken as the
  response if its CRC passes; otherwise the request reading comes first. A
  broadcast request (unit 0) leaves nothing pending.
* Readings are tried in that order: the first whose CRC passes is accepted.
  When a reading still lacks bytes the decoder waits for more input before
  trying the next one, so any chunking of a stream gives the same frames.
* When a reading has no predictable length (unknown function codes, 0x2B
  responses, 0x08 sub-function 0x00, ...), the decoder tries the CRC at every
  length from 4 to 256 bytes, shortest first, once enough bytes are there.
  Such a guess never swallows frames that validate on their own: it is
  refused when a frame of predictable length with a good CRC ("a frame of
  its own") starts inside it and either reaches its end or is followed by a
  second such frame (that parse explains more bytes with valid CRCs; a CRC
  match found by scanning 250 lengths is far likelier chance than two in a
  row).
* A reading still missing bytes is a guess too: it waits for them, unless
  frames of their own inside what it would take line up with the bus (one
  starts or ends at the latest silence, ends the bytes before a silence, is
  followed by another, or two are there; or, as long as no frame has gone on
  across a silence, any one before the silence). Chance CRC matches inside a
  frame cut by a silence weigh less than the frame's own predicted length: a
  match that can be no frame (function code 0 or 0x80, an exception answer
  other than 5 bytes with a code from 1 up: ``FF FF 00 00``, ``FF FF`` being
  the CRC of nothing) never lines up; a match found by a CRC scan lying whole
  before the silence, ending at no boundary the bus marked, does not cut short
  the reading preferred first (the answer to the pending request, else the
  request; a frame of its own there still does); and the answer the pending
  request awaits is cut short only by frames of their own or matches whose
  fields agree with their length.
* Where the readings fail, a CRC that validates at a boundary the bus marks
  (the latest silence, the end of the bytes before a silence or of the
  stream, or where the next frame of its own starts) is a frame whatever its
  fields say: the PDU decoder flags it malformed (libmodbus's quantity-0
  writes, whose byte count disagrees with their length).
* When nothing fits, one byte is skipped into a run of noise; one
  :class:`Noise` is reported per run (before the next frame, at a silence
  when no undecided byte is left before it, or at ``flush``/``reset``), split
  only every ``NOISE_CAP`` bytes. Noise is stamped when its first byte
  arrived, a frame when its last byte did (the read that brought it), however
  late either is decided.

A stream carried in TCP/UDP with a known direction (RTU over TCP) passes
``Direction.C2S`` or ``Direction.S2C``: then only that reading is tried.
Frames always carry C2S (request) or S2C (response), never BUS.

With ``baudrate`` the decoder also looks at inter-chunk silence: a silence
longer than t3.5 (3.5 character times of 11 bits, 1.75 ms above 19200 baud)
counts in ``stats["timing_gaps"]`` and ends the bytes before it as far as
that is safe: leftover noise and length scans are settled at the silence
instead of waiting for 256 bytes, and a reading that would need bytes from
after the silence no longer blocks the next reading; but when no reading
fits the bytes before the silence and one needs more, the decoder still
waits, because USB adapters deliver bytes in bunches and the "silence" may be
their latency. Timing is a hint only. That holds for a scanned reading too:
bytes of unpredictable length with no CRC match yet become noise
at a silence only when a frame of predictable length with a valid CRC starts
after them, before the silence or right at its end (so the next bytes
decide), or a frame found by a CRC scan starts right at the latest silence
(or, on a line whose silences have been real, lies whole before the silence);
otherwise they may be a frame split by the adapter and wait. Bytes whose
readings fail their CRC wait across a silence too when nothing that frames on
its own starts after them: a frame whose fields disagree may be cut there.

Time moves on with :meth:`RtuDecoder.tick` too: t3.5 after the last byte (with
``baudrate``) the bytes held are settled as at a silence seen by the next
chunk, and ``silence`` seconds after it (without or with ``baudrate``) they are
settled as at the end of the stream, so a quiet bus reports its last frame or
noise without waiting for another byte; bytes held ``silence`` seconds are
decided so even while newer ones keep coming (a frame starting in them would
be complete by then). Noise is stamped when its bytes arrived.

The heuristics that look around the bytes at an offset (frames of their own,
lining up with the bus, boundaries, scans across a silence) are
:class:`~mbmon.protocol.rtu_bounds.RtuBounds`, which the decoder owns.

Pure: no I/O, no clocks; time is the ``ts`` given with each chunk or tick.
"""

from __future__ import annotations

from mbmon.model import Direction, Frame, Noise, Stream, fast_constructor
from mbmon.protocol.crc import add_crc
from mbmon.protocol.crc import crc_ok_at as _crc_ok
from mbmon.protocol.pdu import NEED_MORE, decode_pdu, pdu_length
from mbmon.protocol.rtu_bounds import (
    FINAL,
    MAX_ADU,
    MIN_ADU,
    PEEK,
    SILENCE,
    STREAM,
    RtuBounds,
)
from mbmon.protocol.rtu_bounds import REQ_RULES as _REQ_RULES
from mbmon.protocol.rtu_bounds import RESP_RULES as _RESP_RULES
from mbmon.protocol.rtu_bounds import scan_crc as _scan
from mbmon.protocol.stream import StreamDecoder

__all__ = ["MAX_ADU", "NOISE_CAP", "RtuDecoder", "encode_rtu", "t35"]

_C2S = Direction.C2S  # module constants: an enum class attribute costs more per frame
_S2C = Direction.S2C
_new_frame = fast_constructor(Frame)  # one per ADU: about twice as fast as Frame(...)


_NO_RULES: dict[int, int | tuple[int, int]] = {}

NOISE_CAP = 65536
"""A noise run longer than this is reported in pieces of this size."""

# Outcomes of the decision at one offset (lengths > 0 accept a frame).
_WAIT = -1
_SKIP = 0
_WAITING = (_WAIT, False, "")  # the decision "wait for more bytes", made once


def t35(baudrate: int) -> float:
    """The RTU inter-frame silence t3.5 in seconds for ``baudrate`` (11-bit characters)."""
    if baudrate > 19200:
        return 0.00175
    return 3.5 * 11.0 / baudrate


def encode_rtu(unit: int, pdu: bytes) -> bytes:
    """RTU ADU for ``pdu``: unit id + PDU + CRC16 (low byte first)."""
    if not 0 <= unit <= 0xFF:
        raise ValueError(f"unit id {unit} does not fit in a byte")
    return add_crc(bytes((unit,)) + bytes(pdu))


class RtuDecoder(StreamDecoder):
    """Sans-I/O decoder of one RTU byte stream.

    ``direction`` is ``BUS`` for a serial line carrying both directions (the
    decoder tells requests from responses), or C2S/S2C for RTU ADUs carried in
    one TCP/UDP direction. ``baudrate`` enables the timing hints. The decoder
    owns its buffer, the current noise run, the pending request (unit, function
    code) and ``stats``: ``frames``, ``noise_bytes``, ``crc_errors`` (noise runs
    that began where a complete candidate failed its CRC) and ``timing_gaps``.
    It never raises on input bytes.
    """

    __slots__ = (
        "_allow_req",
        "_allow_resp",
        "_bounds",
        "_char",
        "_chunks",
        "_pending",
        "_settled",
        "_silence",
        "_t35",
        "_ticked",
        "baudrate",
        "stats",
    )

    def __init__(
        self,
        stream: Stream,
        direction: Direction = Direction.BUS,
        baudrate: int | None = None,
        silence: float | None = None,
    ) -> None:
        super().__init__(stream, direction)
        self._silence = silence
        self._ticked: float | None = None  # the _last_ts a t3.5 tick settled
        self._settled: float | None = None  # the _last_ts a silence tick settled
        self.baudrate = baudrate
        self._allow_req = direction is not Direction.S2C
        self._allow_resp = direction is not Direction.C2S
        if baudrate is not None and baudrate > 0:
            self._char: float | None = 11.0 / baudrate
            self._t35 = t35(baudrate)
        else:
            self._char = None
            self._t35 = 0.0
        self._pending: tuple[int, int] | None = None
        #: the line-up heuristics, with the latest silence (``mark``) and ``bursty``
        self._bounds = RtuBounds(self._allow_req, self._allow_resp)
        #: (end offset in _buf, arrival time) of each chunk whose bytes _buf holds
        self._chunks: list[tuple[int, float]] = []
        self.stats: dict[str, int] = {
            "frames": 0,
            "noise_bytes": 0,
            "crc_errors": 0,
            "timing_gaps": 0,
        }

    # ------------------------------------------------------------------ public

    def feed(self, data: bytes, ts: float) -> list[Frame | Noise]:
        """Consume one chunk captured at ``ts``; return the frames and noise it completes."""
        out: list[Frame | Noise] = []
        if self._char is not None and self._last_ts is not None and data:
            silence = ts - self._last_ts - len(data) * self._char
            if silence > self._t35:
                self.stats["timing_gaps"] += 1
                self._at_silence(out)
        self._last_ts = ts
        old = len(self._buf)
        if old:
            self._buf += data
            buf: bytes | bytearray = self._buf
        else:
            buf = data  # fast path: decode straight from the chunk, no copy
        pos = self._decode(buf, ts, out, old, STREAM)
        self._keep(buf, pos, old, ts)
        bounds = self._bounds
        if bounds.mark:
            bounds.mark = max(0, bounds.mark - pos)
        return out

    def flush(self, ts: float) -> list[Frame | Noise]:
        """End of stream: decide every buffered byte; what is no frame becomes noise."""
        out = self._settle(ts)
        self._pending = None
        self._last_ts = None
        return out

    def reset(self, ts: float) -> list[Noise]:
        """Drop the buffer and the pending request (e.g. after a gap); report dropped bytes."""
        self.stats["noise_bytes"] += len(self._buf)
        out = self._discard(ts)
        self._chunks = []
        self._bounds.mark = 0
        self._pending = None
        self._last_ts = None
        return out

    def tick(self, now: float) -> list[Frame | Noise]:
        """Time is ``now`` and no byte came since the last chunk: settle what waits.

        t3.5 after the last byte (``baudrate`` known) the bytes held are decided
        as the next chunk would after that silence (scans and noise settled,
        predicted lengths still awaited: USB adapters bunch bytes); ``silence``
        seconds after it everything held is decided as at the end of the stream
        (a partial frame becomes noise). The pending request is kept.
        """
        last = self._last_ts
        if last is None or not (self._buf or self._noise):
            return []
        out: list[Frame | Noise] = []
        if self._char is not None and self._ticked != last and now >= last + self._t35 + 1e-6:
            self._ticked = last
            self._at_silence(out)
        if self._silence is not None and self._settled != last and now >= last + self._silence:
            self._settled = last
            out.extend(self._settle(last))
        if self._silence is not None and self._chunks and now >= self._chunks[0][1] + self._silence:
            self._settle_old(now, self._silence, out)
        return out

    def next_deadline(self) -> float | None:
        """When :meth:`tick` would settle bytes held, or ``None`` when none wait on time."""
        last = self._last_ts
        if last is None or not (self._buf or self._noise):
            return None
        deadline: float | None = None
        if self._char is not None and self._ticked != last:
            deadline = last + self._t35 + 1e-6  # tick settles strictly after t3.5
        if self._silence is not None:
            if self._settled != last:
                at = last + self._silence
                deadline = at if deadline is None else min(deadline, at)
            if self._chunks:  # the oldest byte held has waited ``silence``
                at = self._chunks[0][1] + self._silence
                deadline = at if deadline is None else min(deadline, at)
        return deadline

    # ------------------------------------------------------------------ internals

    def _at_silence(self, out: list[Frame | Noise]) -> None:
        """A silence longer than t3.5 follows the bytes held: decide what it settles.

        The noise run ends here only when no undecided byte is left before the
        silence (those may still join it: one run of noise is one record).
        """
        if self._buf:
            pos = self._decode(self._buf, self._last_ts or 0.0, out, len(self._buf), SILENCE)
            self._drop(pos)
        self._bounds.mark = len(self._buf)
        if not self._buf:
            run = self._take_noise()
            if run is not None:
                out.append(run)

    def _settle_old(self, now: float, silence: float, out: list[Frame | Noise]) -> None:
        """Decide, as at the end of the stream, what starts in the bytes held that
        arrived ``silence`` or more before ``now``: more bytes came after them, yet
        a frame starting there would be complete by now (a frame lasts at most
        ``MAX_ADU`` characters; ``silence`` is above any adapter's latency). So
        bytes that keep coming never hold back a frame, or the noise before it,
        more than ``silence`` past its own arrival. The newer bytes wait on."""
        stop = 0
        for end, ts in self._chunks:
            if ts + silence > now:  # the very sum next_deadline gave: no rounding apart
                break
            stop = end
        if stop:
            pos = self._decode(self._buf, self._last_ts or 0.0, out, len(self._buf), FINAL, stop)
            self._drop(pos)
            self._bounds.mark = max(0, self._bounds.mark - pos)

    def _keep(self, buf: bytes | bytearray, pos: int, old: int, ts: float) -> None:
        """Keep ``buf[pos:]`` (see :class:`StreamDecoder`) and when each kept byte arrived."""
        n = len(buf)
        if pos >= n:
            if self._chunks:
                self._chunks = []
        elif old:
            kept = [(end - pos, t) for end, t in self._chunks if end > pos]
            if n > old:
                kept.append((n - pos, ts))
            self._chunks = kept
        else:
            self._chunks = [(n - pos, ts)]
        super()._keep(buf, pos, old, ts)
        if self._chunks:
            self._buf_ts = self._chunks[0][1]

    def _drop(self, pos: int) -> None:
        """The first ``pos`` bytes of ``_buf`` are decided: drop them."""
        if pos:
            del self._buf[:pos]
            self._chunks = [(end - pos, t) for end, t in self._chunks if end > pos]
            if self._chunks:
                self._buf_ts = self._chunks[0][1]

    def _arrival(self, i: int) -> float:
        """When ``_buf[i]`` arrived (the time of the chunk that brought it)."""
        for end, ts in self._chunks:
            if i < end:
                return ts
        return self._last_ts or 0.0

    def _settle(self, ts: float) -> list[Frame | Noise]:
        """Decide every byte held (frames stamped ``ts``, noise when it arrived)."""
        out: list[Frame | Noise] = []
        if self._buf:
            self._decode(self._buf, ts, out, len(self._buf), FINAL)
            self._buf = bytearray()
            self._chunks = []
        self._bounds.mark = 0
        run = self._take_noise()
        if run is not None:
            out.append(run)
        return out

    def _add_noise(self, byte: int, reason: str, ts: float, out: list[Frame | Noise]) -> None:
        if not self._noise:
            self._noise_reason = reason
            self._noise_ts = ts
            if reason == _BAD_CRC:
                self.stats["crc_errors"] += 1
        self._noise.append(byte)
        self.stats["noise_bytes"] += 1
        if len(self._noise) >= NOISE_CAP:
            out.append(
                Noise(
                    self._noise_ts,
                    self.stream,
                    self.direction,
                    bytes(self._noise),
                    self._noise_reason,
                )
            )
            self._noise = bytearray()
            self._noise_ts = ts

    def _decode(
        self,
        buf: bytes | bytearray,
        ts: float,
        out: list[Frame | Noise],
        old: int,
        mode: int,
        stop: int | None = None,
    ) -> int:
        """Frame ADUs from ``buf``; return the offset of the first undecided byte.
        With ``stop``, decide only what starts before that offset.

        ``buf[:old]`` is what ``_buf`` held (its chunks' times in ``_chunks``),
        the rest arrived at ``ts``: noise is stamped when its first byte
        arrived, a frame when its last byte did (whenever it is decided).

        The common case is decided in the loop itself: the preferred reading
        (the one :meth:`_decide` tries first) has a length that a simple rule of
        :func:`~mbmon.protocol.pdu.pdu_length` predicts, its bytes are all there
        and its CRC passes; :meth:`_decide` would accept exactly that frame, in
        any mode. Everything else (CRC failures, bytes missing, other readings,
        scans, noise) goes to :meth:`_decide`.
        """
        n = len(buf)
        pos = 0
        stream = self.stream
        decide = self._decide
        append = out.append
        new_frame = _new_frame
        crc_ok = _crc_ok
        decode = decode_pdu
        copy = type(buf) is not bytes  # a slice of bytes is bytes already
        req_rules = _REQ_RULES if self._allow_req else _NO_RULES
        resp_rules = _RESP_RULES if self._allow_resp else _NO_RULES
        resp_only = not self._allow_req
        req_only = not self._allow_resp
        pending = self._pending
        frames = 0
        last = n - 1
        bounds = self._bounds
        bounds.new_pass()
        mark = bounds.mark if mode == STREAM else 0
        end_at = n if stop is None else stop
        while pos < end_at:
            if pos < last:
                unit = buf[pos]
                fc = buf[pos + 1]
                if fc & 0x80 or resp_only:
                    is_resp = True
                elif req_only:
                    is_resp = False
                else:
                    is_resp = pending is not None and pending[0] == unit and pending[1] == fc
                rule = (resp_rules if is_resp else req_rules).get(fc)
                if rule is not None:
                    if isinstance(rule, int):
                        end = pos + rule
                    else:
                        at = pos + rule[0]
                        end = pos + rule[1] + buf[at] if at < n else n + 1
                    if end <= n and end - pos <= MAX_ADU and crc_ok(buf, pos, end):
                        if mark and pos < mark < end:
                            bounds.bursty = True
                        if self._noise:
                            append(self._flush_noise_run())
                        raw = bytes(buf[pos:end]) if copy else buf[pos:end]
                        if is_resp:
                            pending = None
                            direction = _S2C
                        else:
                            pending = (unit, fc) if unit != 0 else None
                            direction = _C2S
                        pdu = decode(raw[1:-2], is_resp)
                        when = ts if end > old else self._arrival(end - 1)
                        append(new_frame(when, stream, direction, unit, None, pdu, raw, True))
                        frames += 1
                        pos = end
                        continue
            self._pending = pending
            length, is_resp, reason = decide(buf, pos, n, mode)
            if length > 0:
                if self._noise:
                    append(self._flush_noise_run())
                end = pos + length
                if mark and pos < mark < end:
                    bounds.bursty = True
                raw = bytes(buf[pos:end]) if copy else buf[pos:end]
                unit = raw[0]
                pdu = decode(raw[1:-2], is_resp)
                if is_resp:
                    pending = None
                    direction = _S2C
                else:
                    pending = (unit, raw[1]) if unit != 0 else None
                    direction = _C2S
                when = ts if end > old else self._arrival(end - 1)
                append(new_frame(when, stream, direction, unit, None, pdu, raw, True))
                frames += 1
                pos = end
            elif length == _WAIT:
                break
            else:
                self._add_noise(buf[pos], reason, self._arrival(pos) if pos < old else ts, out)
                pos += 1
        self._pending = pending
        if frames:
            self.stats["frames"] += frames
        return pos

    def _decide(self, buf: bytes | bytearray, pos: int, n: int, mode: int) -> tuple[int, bool, str]:
        """Decide what starts at ``pos``.

        Returns (ADU length, is response, "") for a frame, (_WAIT, False, "")
        when more bytes are needed, or (_SKIP, False, reason) for a noise byte.

        In order: a reading whose predicted length is there with a valid CRC; a
        reading still missing bytes waits, unless a frame that frames on its
        own starts inside it, lined up with a boundary of the bus
        (:meth:`RtuBounds.lines_up`); a reading of unpredictable length is scanned for
        its CRC; where the readings fail, a CRC that validates at a boundary the
        bus marks is a frame whatever its fields say (:meth:`RtuBounds.boundary`; the
        PDU decoder flags them malformed); the rest is noise.
        """
        avail = n - pos
        if avail < 2:
            return (_SKIP, False, _TRUNCATED) if mode == FINAL else _WAITING
        fc = buf[pos + 1]
        readings = self._readings(buf[pos], fc)
        if not readings or fc == 0 or fc == 0x80:
            return _SKIP, False, f"no valid frame (function code 0x{fc:02X})"
        total, is_resp, crc_failed, far, unpredictable, first_far = self._try_readings(
            buf, pos, avail, readings, mode
        )
        if total:
            return total, is_resp, ""
        cut = False  # a reading missing bytes would swallow a frame lined up with the bus
        if far and mode != FINAL:
            # USB adapters bunch bytes: a frame may go on after a silence, so wait;
            # but not for bytes that frame on their own at the bus's boundaries. A
            # CRC match lying whole before the silence (at no boundary the bus
            # marked) does not cut short the reading preferred first, nor one whose
            # fields disagree with its length the answer the pending request awaits
            awaited = first_far and readings[0]
            if not self._bounds.lines_up(buf, pos, n, mode, far, not first_far, awaited):
                return _WAITING
            cut = True
        elif unpredictable:
            awaited = unpredictable[0] and readings[0]  # the answer the pending request awaits
            decided = self._decide_scan(buf, pos, n, mode, unpredictable[0], awaited)
            if decided is not None:
                return decided
        if crc_failed or cut:
            decided = self._decide_boundary(buf, pos, n, mode, readings)
            if decided is not None:
                return decided
        return _SKIP, False, _reason(fc, crc_failed, cut, far > 0, bool(unpredictable))

    def _readings(self, unit: int, fc: int) -> tuple[bool, ...]:
        """The readings of a frame from ``unit`` with ``fc`` in order of preference
        (True: response): the answer to the pending request first, else the request."""
        if fc & 0x80:
            return (True,) if self._allow_resp else ()
        if not self._allow_resp:
            return (False,)
        if not self._allow_req:
            return (True,)
        pending = self._pending
        if pending is not None and pending[0] == unit and pending[1] == fc:
            return (True, False)
        return (False, True)

    def _try_readings(
        self, buf: bytes | bytearray, pos: int, avail: int, readings: tuple[bool, ...], mode: int
    ) -> tuple[int, bool, bool, int, list[bool] | None, bool]:
        """Try each reading's predicted length and CRC at ``pos``, in order.

        Returns ``(ADU length, is response, crc failed, far, unpredictable,
        first far)``: a length > 0 when a reading's CRC passes; else ``far`` > 0
        is where the longest reading still missing bytes would end (in ``STREAM``
        mode the first one stops the others being tried: a later reading must
        not be taken before it is known), ``unpredictable`` the readings of no
        predictable length (for a CRC scan), and ``first far`` whether the
        reading preferred first is one still missing bytes.
        """
        peek = buf[pos + 1 : pos + 1 + PEEK]
        far = 0
        crc_failed = False
        unpredictable: list[bool] | None = None
        first_far = False
        for i, is_resp in enumerate(readings):
            plen = pdu_length(peek, is_resp)
            if plen == NEED_MORE and avail - 1 > PEEK:
                plen = pdu_length(buf[pos + 1 : pos + MAX_ADU], is_resp)
            if plen is None:
                unpredictable = [is_resp] if unpredictable is None else [*unpredictable, is_resp]
                continue
            total = MAX_ADU if plen == NEED_MORE else plen + 3
            if plen != NEED_MORE and (total > MAX_ADU or plen < 1):
                continue
            if plen == NEED_MORE or total > avail:
                far = max(far, pos + total)
                first_far = first_far or not i
                if mode == STREAM:
                    break
                continue
            if _crc_ok(buf, pos, pos + total):
                return total, is_resp, False, 0, None, False
            crc_failed = True
        return 0, False, crc_failed, far, unpredictable, first_far

    def _decide_scan(
        self, buf: bytes | bytearray, pos: int, n: int, mode: int, is_resp: bool, awaited: bool
    ) -> tuple[int, bool, str] | None:
        """The decision for bytes of no predictable length at ``pos``: the shortest
        CRC match (unless it swallows frames), or wait; ``None`` when neither (the
        caller goes on to noise). ``awaited``: the bytes read as the answer the
        pending request awaits (a CRC match whose fields disagree with its length
        does not end its wait at a silence)."""
        avail = n - pos
        limit = min(MAX_ADU, avail)
        found = _scan(buf, pos, limit) if limit >= MIN_ADU else 0
        if found:
            crossed = self._bounds.crosses_frames(buf, pos, pos + found, n, mode)
            if crossed < 0:
                return _WAITING
            if not crossed:
                return found, is_resp, ""
            return _SKIP, False, _CROSSED
        if avail < MAX_ADU and mode != FINAL:
            # No CRC match yet: the frame may go on in bytes still to come, also
            # after a silence (USB adapters bunch bytes). Before a silence it is
            # noise only when a frame of its own starts after it and no later
            # than the silence, or frames line up.
            mark = n if mode == SILENCE else self._bounds.mark
            if (
                pos >= mark or self._bounds.frame_within(buf, pos + 1, mark, n, mode) != 1
            ) and not self._bounds.lines_up(buf, pos, n, mode, pos + MAX_ADU, True, awaited):
                return _WAITING
        return None

    def _decide_boundary(
        self, buf: bytes | bytearray, pos: int, n: int, mode: int, readings: tuple[bool, ...]
    ) -> tuple[int, bool, str] | None:
        """Where the readings failed: a CRC that validates at a boundary the bus marks
        is a frame whatever its fields say, or wait for one; ``None`` for noise."""
        found = self._bounds.boundary(buf, pos, n, mode)
        if found < 0 or (not found and self._bounds.may_go_on(buf, pos, n, mode)):
            return _WAITING
        if not found:
            return None
        # the reading whose length it has, if any (a reading missing bytes stopped
        # the others being tried): the direction any chunking gives
        whole = buf[pos + 1 : pos + found]
        for is_resp in readings:
            plen = pdu_length(whole, is_resp)
            if plen is not None and plen != NEED_MORE and plen + 3 == found:
                return found, is_resp, ""
        return found, readings[0], ""


def _reason(fc: int, crc_failed: bool, cut: bool, incomplete: bool, unpredictable: bool) -> str:
    """Why the byte at an offset is noise, from what its readings found."""
    if crc_failed:
        return _BAD_CRC
    if cut:
        return _CUT
    if incomplete:
        return _TRUNCATED
    if unpredictable:
        return f"no valid frame (unknown function code 0x{fc:02X})"
    return f"no valid frame (function code 0x{fc:02X})"


_CROSSED = "no valid frame (a CRC match by scanning would swallow valid frames)"
_BAD_CRC = "no valid frame (bad CRC)"
_TRUNCATED = "truncated frame at end of stream"
_CUT = "no valid frame (cut short by the next frame)"
