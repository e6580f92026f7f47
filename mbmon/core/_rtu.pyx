# cython: language_level=3
"""RTU framing in the compiled core: :class:`mbmon.protocol.rtu.RtuDecoder`'s
timing-free framing, without a Python object per frame.

:class:`RtuCore` frames one RTU byte stream (a bus, or one direction of RTU over
TCP/UDP) exactly as the reference decoder does when no baud rate is given: the
same frames, the same noise runs with the same reasons, the same times. It owns
its buffer, the noise run, the pending request, the arrival times of the bytes
it holds and the per-pass memos of the line-up heuristics
(:mod:`mbmon.protocol.rtu_bounds`, transliterated for the timing-free case: no
silence mark, never bursty, passes in the ``STREAM`` and ``FINAL`` modes only).

Two outputs, one framing path:

* ``push(data, ts)`` / ``push_flush(ts)`` / ``push_tick(now)`` / ``push_reset(ts)``
  frame into packed records (``take()``: 16 bytes per frame or noise run, the
  frames' bytes concatenated, the few :class:`~mbmon.model.Noise` objects): no
  Python object per frame;
* ``feed`` / ``flush`` / ``tick`` / ``reset`` (the pipeline's ``StreamDecoding``)
  turn those records into :class:`~mbmon.model.Frame` and ``Noise`` objects, a
  drop-in for the reference decoder.

With a baud rate the reference's timing rules apply (silences, t3.5 ticks, USB
bursts): the core does not cover them and refuses (``ValueError``) so the caller
builds the reference decoder instead (:func:`mbmon.core.rtu_decoder`).

Every index that comes from the input (a byte count, a predicted length) is
checked against the bytes present before it is read.
"""

from libc.stdlib cimport free, realloc
from libc.string cimport memcpy
from cpython.bytes cimport PyBytes_FromStringAndSize

import struct

from mbmon.model import Direction, Frame, Noise, fast_constructor
from mbmon.protocol import rtu as _ref
from mbmon.protocol.crc import CRC_TABLE
from mbmon.protocol.functions import FUNCTIONS, NEED_MORE as _PY_NEED_MORE, derived
from mbmon.protocol.lengths import pdu_length as _py_pdu_length
from mbmon.protocol.lengths import simple_length_rules
from mbmon.protocol.pdu import decode_pdu
from mbmon.protocol.rtu_bounds import FINAL as _PY_FINAL, MAX_ADU as _PY_MAX_ADU
from mbmon.protocol.rtu_bounds import MIN_ADU as _PY_MIN_ADU, PEEK as _PY_PEEK
from mbmon.protocol.rtu_bounds import REQ_RULES, RESP_RULES, STREAM as _PY_STREAM
from mbmon.protocol.rtu_bounds import RtuBounds as _RefBounds

_new_frame = fast_constructor(Frame)
_C2S = Direction.C2S
_S2C = Direction.S2C

DEF_CHECK = (_PY_MAX_ADU, _PY_MIN_ADU, _PY_PEEK, _PY_STREAM, _PY_FINAL, _PY_NEED_MORE)

cdef enum:
    MAX_ADU = 256
    MIN_ADU = 4
    PEEK = 16
    STREAM = 0
    FINAL = 2
    NEED_MORE = -1
    NO_LENGTH = -1000000  # pdu_length's None
    WAIT = -1
    SKIP = 0

if DEF_CHECK != (MAX_ADU, MIN_ADU, PEEK, STREAM, FINAL, NEED_MORE):
    raise ImportError("mbmon.core._rtu was built for other RTU constants than the reference's")

NOISE_CAP = _ref.NOISE_CAP
cdef Py_ssize_t _NOISE_CAP = _ref.NOISE_CAP

# The reference's noise reasons (the strings themselves, so a change there is followed)
_BAD_CRC = _ref._BAD_CRC
_TRUNCATED = _ref._TRUNCATED
_CUT = _ref._CUT
_CROSSED = _ref._CROSSED
_R_FC = [f"no valid frame (function code 0x{fc:02X})" for fc in range(256)]
_R_UNKNOWN = [f"no valid frame (unknown function code 0x{fc:02X})" for fc in range(256)]
PACKED = struct.Struct("<BBHId")  # one record of take(): kind, pad, length, offset, time

cdef unsigned short CRC[256]
for _i in range(256):
    CRC[_i] = CRC_TABLE[_i]


def _reference_rules() -> tuple:
    """Two rules of the reference's line-up heuristics that are changing while this
    module is merged, read off the reference itself so the framer follows whichever
    it has: whether an exception answer with exception code 0 is a frame of its own
    (asked of ``RtuBounds._standalone``), and whether ``RtuBounds._lined_up``
    remembers its answer per ``(fits, within)``."""
    import inspect

    exc0 = bytes((0x11, 0x83, 0x00))
    crc = 0xFFFF
    for b in exc0:
        crc = (crc >> 8) ^ CRC_TABLE[(crc ^ b) & 0xFF]
    adu = exc0 + bytes((crc & 0xFF, crc >> 8))
    standalone = _RefBounds(True, True)._standalone(adu, 0, len(adu), _PY_FINAL) > 0
    keyed = "within" in inspect.signature(_RefBounds._lined_up).parameters
    return standalone, keyed


_EXC0_STANDALONE, _MEMO_KEYED = _reference_rules()
cdef bint EXC0_STANDALONE = _EXC0_STANDALONE
cdef bint MEMO_KEYED = _MEMO_KEYED

# Length tables, [response][function code], copied out of the reference's tables by
# _rebuild (again when a function code is registered). ADU rules as the framing loop
# reads them (REQ_RULES / RESP_RULES): kind 0 none, 1 fixed ADU length A, 2 ADU length
# B + adu[A]. PDU rules as pdu_length reads them: kind 0 no predictable length, 1
# fixed PDU length A, 2 PDU length B + pdu[A], 3 a function (asked in Python).
cdef int ADU_KIND[2][256]
cdef int ADU_A[2][256]
cdef int ADU_B[2][256]
cdef int PDU_KIND[2][256]
cdef int PDU_A[2][256]
cdef int PDU_B[2][256]


@derived
def _rebuild() -> None:
    """Copy the length rules out of the reference's tables (run again by ``register``)."""
    cdef int r, fc
    for r in range(2):
        adu = RESP_RULES if r else REQ_RULES
        simple = simple_length_rules(bool(r))
        for fc in range(256):
            rule = adu.get(fc)
            ADU_KIND[r][fc] = 0 if rule is None else (1 if isinstance(rule, int) else 2)
            ADU_A[r][fc] = 0 if rule is None else (rule if isinstance(rule, int) else rule[0])
            ADU_B[r][fc] = 0 if rule is None or isinstance(rule, int) else rule[1]
            rule = simple.get(fc)
            if rule is None:
                spec = FUNCTIONS.get(fc)
                length = None
                if spec is not None:
                    length = spec.response_length if r else spec.request_length
                PDU_KIND[r][fc] = 0 if length is None else 3
                PDU_A[r][fc] = PDU_B[r][fc] = 0
            elif isinstance(rule, int):
                PDU_KIND[r][fc] = 1
                PDU_A[r][fc] = rule
                PDU_B[r][fc] = 0
            else:
                PDU_KIND[r][fc] = 2
                PDU_A[r][fc] = rule[0]
                PDU_B[r][fc] = rule[1]


cdef inline bint crc_ok(const unsigned char* p, Py_ssize_t n, Py_ssize_t start, Py_ssize_t end) noexcept nogil:
    """``p[start:end]`` ends with the CRC16 of the bytes before it (False when the range
    is not inside ``p[:n]`` or shorter than a CRC)."""
    cdef unsigned int crc = 0xFFFF
    cdef Py_ssize_t i
    if start < 0 or end > n or end - start < 2:
        return False
    for i in range(start, end - 2):
        crc = (crc >> 8) ^ CRC[(crc ^ p[i]) & 0xFF]
    return p[end - 2] == (crc & 0xFF) and p[end - 1] == (crc >> 8)


cdef Py_ssize_t scan_crc(const unsigned char* p, Py_ssize_t n, Py_ssize_t start, Py_ssize_t limit) noexcept nogil:
    """Shortest length L in MIN_ADU..limit with a valid CRC at ``p[start:start+L]``, else 0
    (:func:`mbmon.protocol.rtu_bounds.scan_crc`)."""
    cdef unsigned int crc = 0xFFFF
    cdef Py_ssize_t length, i
    cdef unsigned char lo
    if limit > n - start:
        limit = n - start
    if limit < MIN_ADU or start < 0:
        return 0
    crc = (crc >> 8) ^ CRC[(crc ^ p[start]) & 0xFF]
    crc = (crc >> 8) ^ CRC[(crc ^ p[start + 1]) & 0xFF]
    for length in range(MIN_ADU, limit + 1):
        i = start + length - 2
        lo = p[i]
        if lo == (crc & 0xFF) and p[i + 1] == (crc >> 8):
            return length
        crc = (crc >> 8) ^ CRC[(crc ^ lo) & 0xFF]
    return 0


cdef Py_ssize_t pdu_len(const unsigned char* p, Py_ssize_t start, Py_ssize_t m, int resp) except? -2000000:
    """:func:`mbmon.protocol.lengths.pdu_length` of ``p[start:start+m]`` (the caller
    guarantees those bytes are there): NEED_MORE, NO_LENGTH (None) or the length."""
    cdef int fc, kind, a
    if m <= 0:
        return NEED_MORE
    fc = p[start]
    if fc & 0x80:
        return 2 if resp else NO_LENGTH
    kind = PDU_KIND[resp][fc]
    if kind == 1:
        return PDU_A[resp][fc]
    if kind == 2:
        a = PDU_A[resp][fc]
        return NEED_MORE if m <= a else PDU_B[resp][fc] + p[start + a]
    if kind == 0:
        return NO_LENGTH
    got = _py_pdu_length(PyBytes_FromStringAndSize(<const char*>p + start, m), bool(resp))
    return NO_LENGTH if got is None else got


cdef struct Rec:
    unsigned char kind  # 0 request frame, 1 response frame, 2 noise run
    unsigned char pad
    unsigned short length  # frame bytes (noise: 0)
    unsigned int offset  # frame: offset in the raw bytes; noise: index in the noise list
    double ts


cdef class RtuCore:
    """One RTU byte stream framed as :class:`mbmon.protocol.rtu.RtuDecoder` frames it
    without a baud rate (see the module docstring). ``stats`` and ``buffered`` are the
    reference's."""

    cdef readonly object stream
    cdef readonly object direction
    cdef readonly object baudrate
    cdef public dict stats
    cdef bint allow_req, allow_resp
    cdef bint has_silence
    cdef double silence
    cdef bytearray _buf
    cdef double _buf_ts
    cdef object _last_ts  # None or float
    cdef object _settled  # None or float: the _last_ts a silence tick settled
    cdef list _chunks  # (end offset in _buf, arrival time) of each chunk _buf holds
    cdef bytearray _noise
    cdef object _noise_reason
    cdef double _noise_ts
    cdef int pend_unit, pend_fc  # the pending request (-1: none)
    # per-pass memos of the line-up heuristics (RtuBounds._near, ._lined)
    cdef bint has_near, has_lined
    cdef Py_ssize_t near_lo, near_k, near_found
    cdef Py_ssize_t lined_lo, lined_first, lined_k, lined_state
    cdef bint lined_fits, lined_within
    # the decision's side results (_decide): is response, reason
    cdef bint d_resp
    cdef object d_reason
    # packed output
    cdef Rec* recs
    cdef Py_ssize_t nrecs, caprecs
    cdef unsigned char* raw
    cdef Py_ssize_t nraw, capraw
    cdef list noises
    cdef Py_ssize_t frames_pass

    def __cinit__(self) -> None:
        self.recs = NULL
        self.raw = NULL
        self.nrecs = self.caprecs = self.nraw = self.capraw = 0

    def __dealloc__(self) -> None:
        free(self.recs)
        free(self.raw)

    def __init__(self, stream, direction=Direction.BUS, baudrate=None, silence=None):
        if baudrate is not None and baudrate > 0:
            raise ValueError("the compiled RTU framer does not cover a baud rate's timing rules")
        self.stream = stream
        self.direction = direction
        self.baudrate = baudrate
        self.allow_req = direction is not Direction.S2C
        self.allow_resp = direction is not Direction.C2S
        self.has_silence = silence is not None
        self.silence = silence if silence is not None else 0.0
        self._buf = bytearray()
        self._buf_ts = 0.0
        self._last_ts = None
        self._settled = None
        self._chunks = []
        self._noise = bytearray()
        self._noise_reason = ""
        self._noise_ts = 0.0
        self.pend_unit = self.pend_fc = -1
        self.noises = []
        self.stats = {"frames": 0, "noise_bytes": 0, "crc_errors": 0, "timing_gaps": 0}

    @property
    def buffered(self) -> int:
        """Bytes held: undecided bytes plus the noise run not yet reported."""
        return len(self._buf) + len(self._noise)

    # ------------------------------------------------------------ packed output

    cdef int _rec(self, unsigned char kind, Py_ssize_t length, Py_ssize_t offset, double ts) except -1:
        cdef Py_ssize_t cap
        cdef Rec* grown
        if self.nrecs == self.caprecs:
            cap = 1024 if self.caprecs == 0 else 2 * self.caprecs
            grown = <Rec*>realloc(self.recs, cap * sizeof(Rec))
            if grown == NULL:
                raise MemoryError()
            self.recs = grown
            self.caprecs = cap
        self.recs[self.nrecs].kind = kind
        self.recs[self.nrecs].pad = 0
        self.recs[self.nrecs].length = <unsigned short>length
        self.recs[self.nrecs].offset = <unsigned int>offset
        self.recs[self.nrecs].ts = ts
        self.nrecs += 1
        return 0

    cdef int _emit_frame(self, const unsigned char* p, Py_ssize_t pos, Py_ssize_t end, bint resp, double when) except -1:
        cdef Py_ssize_t length = end - pos
        cdef Py_ssize_t cap
        cdef unsigned char* grown
        if self.nraw + length > 0xFFFFFFFF:  # a record's offset is 32 bits
            raise OverflowError("more than 4 GiB of frames framed without take() or clear()")
        if self.nraw + length > self.capraw:
            cap = 65536 if self.capraw == 0 else 2 * self.capraw
            while cap < self.nraw + length:
                cap *= 2
            grown = <unsigned char*>realloc(self.raw, cap)
            if grown == NULL:
                raise MemoryError()
            self.raw = grown
            self.capraw = cap
        memcpy(self.raw + self.nraw, p + pos, length)
        self._rec(1 if resp else 0, length, self.nraw, when)
        self.nraw += length
        return 0

    cdef int _emit_noise(self, object run) except -1:
        self._rec(2, 0, len(self.noises), run.ts)
        self.noises.append(run)
        return 0

    def take(self):
        """The packed output since the last ``take``/``clear``: ``(records, raw, noise)``:
        16 bytes per record (``<BBHId``: kind 0 request, 1 response, 2 noise; frame
        length; offset of the frame in ``raw`` or index in ``noise``; time), the frames'
        bytes, the noise runs."""
        recs = PyBytes_FromStringAndSize(<const char*>self.recs, self.nrecs * sizeof(Rec))
        raw = PyBytes_FromStringAndSize(<const char*>self.raw, self.nraw)
        noises = self.noises
        self.clear()
        return recs, raw, noises

    def clear(self) -> None:
        """Drop the packed output (a caller that only counts)."""
        self.nrecs = self.nraw = 0
        self.noises = []

    @property
    def pending_records(self) -> int:
        """Records framed and not yet taken."""
        return self.nrecs

    cdef list _objects(self):
        """The packed output as the reference's Frame and Noise objects, in order."""
        cdef list out = []
        cdef Py_ssize_t i
        cdef Rec* r
        cdef bint resp
        stream = self.stream
        for i in range(self.nrecs):
            r = &self.recs[i]
            if r.kind == 2:
                out.append(self.noises[r.offset])
                continue
            resp = r.kind == 1
            raw = PyBytes_FromStringAndSize(<const char*>self.raw + r.offset, r.length)
            out.append(
                _new_frame(
                    r.ts,
                    stream,
                    _S2C if resp else _C2S,
                    self.raw[r.offset],
                    None,
                    decode_pdu(raw[1 : r.length - 2], resp),
                    raw,
                    True,
                )
            )
        self.clear()
        return out

    # ------------------------------------------------------------ the decoder's API

    def feed(self, data, double ts) -> list:
        """Consume one chunk captured at ``ts``; the frames and noise it completes."""
        self.push(data, ts)
        return self._objects()

    def flush(self, double ts) -> list:
        """End of stream: decide every buffered byte; what is no frame becomes noise."""
        self.push_flush(ts)
        return self._objects()

    def reset(self, double ts) -> list:
        """Drop the buffer and the pending request (a gap); report the dropped bytes."""
        self.push_reset(ts)
        return self._objects()

    def tick(self, double now) -> list:
        """Time is ``now``: ``silence`` seconds after the last byte what is held is
        settled as at the end of the stream (the reference's ``tick`` without a baud rate)."""
        self.push_tick(now)
        return self._objects()

    def next_deadline(self):
        """When :meth:`tick` would settle bytes held, or ``None``."""
        last = self._last_ts
        if last is None or not (self._buf or self._noise):
            return None
        deadline = None
        if self.has_silence:
            if self._settled != last:
                deadline = last + self.silence
            if self._chunks:
                at = self._chunks[0][1] + self.silence
                deadline = at if deadline is None else min(deadline, at)
        return deadline

    # ------------------------------------------------------------ packed entries

    def push(self, data, double ts) -> None:
        """:meth:`feed` into the packed output."""
        cdef Py_ssize_t old, pos
        self._last_ts = ts
        old = len(self._buf)
        if old:
            self._buf += data
            buf = self._buf
        else:
            buf = data if type(data) is bytes else bytes(data)
        pos = self._decode(buf, ts, old, STREAM, -1)
        self._keep(buf, pos, old, ts)

    def push_flush(self, double ts) -> None:
        """:meth:`flush` into the packed output."""
        self._settle(ts)
        self.pend_unit = self.pend_fc = -1
        self._last_ts = None

    def push_reset(self, double ts) -> None:
        """:meth:`reset` into the packed output."""
        self.stats["noise_bytes"] += len(self._buf)
        if self._buf:
            if not self._noise:
                self._noise_reason = "discarded after gap"
                self._noise_ts = self._buf_ts
            self._noise += self._buf
            self._buf = bytearray()
        self._take_noise()
        self._chunks = []
        self.pend_unit = self.pend_fc = -1
        self._last_ts = None

    def push_tick(self, double now) -> None:
        """:meth:`tick` into the packed output."""
        last = self._last_ts
        if last is None or not (self._buf or self._noise):
            return
        if self.has_silence and self._settled != last and now >= last + self.silence:
            self._settled = last
            self._settle(last)
        if self.has_silence and self._chunks and now >= self._chunks[0][1] + self.silence:
            self._settle_old(now)

    # ------------------------------------------------------------ internals

    cdef _settle(self, double ts):
        if self._buf:
            self._decode(self._buf, ts, len(self._buf), FINAL, -1)
            self._buf = bytearray()
            self._chunks = []
        self._take_noise()

    cdef _settle_old(self, double now):
        cdef Py_ssize_t stop = 0, pos
        for end, t in self._chunks:
            if t + self.silence > now:
                break
            stop = end
        if stop:
            last = self._last_ts
            pos = self._decode(self._buf, last if last is not None else 0.0, len(self._buf), FINAL, stop)
            self._drop(pos)

    cdef _take_noise(self):
        if self._noise:
            self._flush_noise_run()

    cdef _flush_noise_run(self):
        self._emit_noise(
            Noise(self._noise_ts, self.stream, self.direction, bytes(self._noise), self._noise_reason)
        )
        self._noise = bytearray()

    cdef _keep(self, object buf, Py_ssize_t pos, Py_ssize_t old, double ts):
        """Keep ``buf[pos:]`` undecided, and when each kept byte arrived (the reference's
        ``RtuDecoder._keep`` and ``StreamDecoder._keep``)."""
        cdef Py_ssize_t n = len(buf)
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
        if buf is self._buf:
            del self._buf[:pos]
            if pos >= old:
                self._buf_ts = ts
        elif pos < n:
            self._buf = bytearray(buf[pos:])
            self._buf_ts = ts
        if self._chunks:
            self._buf_ts = self._chunks[0][1]

    cdef _drop(self, Py_ssize_t pos):
        if pos:
            del self._buf[:pos]
            self._chunks = [(end - pos, t) for end, t in self._chunks if end > pos]
            if self._chunks:
                self._buf_ts = self._chunks[0][1]

    cdef double _arrival(self, Py_ssize_t i):
        for end, ts in self._chunks:
            if i < end:
                return ts
        last = self._last_ts
        return last if last is not None else 0.0

    cdef int _add_noise(self, int byte, object reason, double ts) except -1:
        if not self._noise:
            self._noise_reason = reason
            self._noise_ts = ts
            if reason == _BAD_CRC:
                self.stats["crc_errors"] += 1
        self._noise.append(byte)
        self.stats["noise_bytes"] += 1
        if len(self._noise) >= _NOISE_CAP:
            self._flush_noise_run()
            self._noise_ts = ts
        return 0

    cdef Py_ssize_t _decode(self, object buf, double ts, Py_ssize_t old, int mode, Py_ssize_t stop) except -1:
        """Frame ADUs from ``buf`` (the reference's ``RtuDecoder._decode``); the offset of
        the first undecided byte. ``stop`` >= 0: decide only what starts before it."""
        cdef const unsigned char[::1] view
        cdef const unsigned char* p
        cdef Py_ssize_t n = len(buf)
        cdef Py_ssize_t pos = 0, end, at, length, end_at, last = n - 1
        cdef int unit, fc, kind, r, pu = self.pend_unit, pf = self.pend_fc
        cdef bint is_resp
        cdef bint resp_only = not self.allow_req
        cdef bint req_only = not self.allow_resp
        cdef Py_ssize_t frames = 0
        self.has_near = self.has_lined = False  # a new pass: forget the memos
        if n == 0:
            return 0
        view = buf
        p = &view[0]
        end_at = n if stop < 0 else stop
        while pos < end_at:
            if pos < last:
                unit = p[pos]
                fc = p[pos + 1]
                if fc & 0x80 or resp_only:
                    is_resp = True
                elif req_only:
                    is_resp = False
                else:
                    is_resp = pu >= 0 and pu == unit and pf == fc
                r = 1 if is_resp else 0
                kind = ADU_KIND[r][fc] if (self.allow_resp if is_resp else self.allow_req) else 0
                if kind:
                    if kind == 1:
                        end = pos + ADU_A[r][fc]
                    else:
                        at = pos + ADU_A[r][fc]
                        end = pos + ADU_B[r][fc] + p[at] if at < n else n + 1
                    if end <= n and end - pos <= MAX_ADU and crc_ok(p, n, pos, end):
                        if self._noise:
                            self._flush_noise_run()
                        if is_resp:
                            pu = pf = -1
                        elif unit != 0:
                            pu, pf = unit, fc
                        else:
                            pu = pf = -1
                        self._emit_frame(p, pos, end, is_resp, ts if end > old else self._arrival(end - 1))
                        frames += 1
                        pos = end
                        continue
            self.pend_unit, self.pend_fc = pu, pf
            length = self._decide(p, pos, n, mode)
            if length > 0:
                if self._noise:
                    self._flush_noise_run()
                end = pos + length
                unit = p[pos]
                if self.d_resp:
                    pu = pf = -1
                elif unit != 0:
                    pu, pf = unit, p[pos + 1]
                else:
                    pu = pf = -1
                self._emit_frame(p, pos, end, self.d_resp, ts if end > old else self._arrival(end - 1))
                frames += 1
                pos = end
            elif length == WAIT:
                break
            else:
                self._add_noise(p[pos], self.d_reason, self._arrival(pos) if pos < old else ts)
                pos += 1
        self.pend_unit, self.pend_fc = pu, pf
        if frames:
            self.stats["frames"] += frames
        return pos

    # ------------------------------------------------------------ the decision
    # RtuDecoder._decide and the RtuBounds heuristics it asks, for mark = 0 (no
    # silence is ever marked without a baud rate), bursty False, modes STREAM/FINAL.

    cdef Py_ssize_t _decide(self, const unsigned char* p, Py_ssize_t pos, Py_ssize_t n, int mode) except -2:
        """What starts at ``pos``: a frame's length (``d_resp`` its direction), WAIT, or
        SKIP (``d_reason`` why the byte is noise)."""
        cdef Py_ssize_t avail = n - pos, total, far, found
        cdef int fc, nread, r0, r1, unpred
        cdef bint crc_failed, cut = False, first_far
        self.d_resp = False
        if avail < 2:
            if mode == FINAL:
                self.d_reason = _TRUNCATED
                return SKIP
            return WAIT
        fc = p[pos + 1]
        nread = self._readings(p[pos], fc, &r0, &r1)
        if nread == 0 or fc == 0 or fc == 0x80:
            self.d_reason = _R_FC[fc]
            return SKIP
        # _try_readings
        far = 0
        crc_failed = False
        unpred = -1  # the first reading of no predictable length (-1: none)
        total = self._try(p, pos, n, r0, mode, &far, &crc_failed, &unpred)
        first_far = far > 0  # the reading preferred first still misses bytes
        if total == 0 and nread == 2 and not (mode == STREAM and far):
            total = self._try(p, pos, n, r1, mode, &far, &crc_failed, &unpred)
        if total > 0:
            return total
        if far and mode != FINAL:
            if self._lined_up(p, pos, n, mode, far, first_far and r0 == 1, not first_far) != 1:
                return WAIT
            cut = True
        elif unpred >= 0:
            found = self._decide_scan(p, pos, n, mode, unpred, unpred == 1 and r0 == 1)
            if found != -3:
                return found
        if crc_failed or cut:
            found = self._decide_boundary(p, pos, n, mode, nread, r0, r1)
            if found != -3:
                return found
        if crc_failed:
            self.d_reason = _BAD_CRC
        elif cut:
            self.d_reason = _CUT
        elif far > 0:
            self.d_reason = _TRUNCATED
        elif unpred >= 0:
            self.d_reason = _R_UNKNOWN[fc]
        else:
            self.d_reason = _R_FC[fc]
        return SKIP

    cdef int _readings(self, int unit, int fc, int* r0, int* r1) noexcept:
        """The readings in order of preference (1: response); how many."""
        if fc & 0x80:
            r0[0] = 1
            return 1 if self.allow_resp else 0
        if not self.allow_resp:
            r0[0] = 0
            return 1
        if not self.allow_req:
            r0[0] = 1
            return 1
        if self.pend_unit >= 0 and self.pend_unit == unit and self.pend_fc == fc:
            r0[0], r1[0] = 1, 0
        else:
            r0[0], r1[0] = 0, 1
        return 2

    cdef Py_ssize_t _try(self, const unsigned char* p, Py_ssize_t pos, Py_ssize_t n, int resp, int mode,
                         Py_ssize_t* far, bint* crc_failed, int* unpred) except -2:
        """One reading of ``RtuDecoder._try_readings``: its ADU length when its CRC
        passes, else 0 (``far``, ``crc_failed``, ``unpred`` updated)."""
        cdef Py_ssize_t avail = n - pos, plen, total, m
        m = avail - 1 if avail - 1 < PEEK else PEEK
        plen = pdu_len(p, pos + 1, m, resp)
        if plen == NEED_MORE and avail - 1 > PEEK:
            m = avail - 1 if avail - 1 < MAX_ADU - 1 else MAX_ADU - 1
            plen = pdu_len(p, pos + 1, m, resp)
        if plen == NO_LENGTH:
            if unpred[0] < 0:
                unpred[0] = resp
            return 0
        total = MAX_ADU if plen == NEED_MORE else plen + 3
        if plen != NEED_MORE and (total > MAX_ADU or plen < 1):
            return 0
        if plen == NEED_MORE or total > avail:
            if pos + total > far[0]:
                far[0] = pos + total
            return 0
        if crc_ok(p, n, pos, pos + total):
            self.d_resp = resp
            return total
        crc_failed[0] = True
        return 0

    cdef Py_ssize_t _decide_scan(self, const unsigned char* p, Py_ssize_t pos, Py_ssize_t n, int mode, int resp,
                                 bint awaited) except -2:
        """``RtuDecoder._decide_scan``: a length, WAIT, SKIP, or -3 (go on to noise)."""
        cdef Py_ssize_t avail = n - pos, limit, found
        cdef int crossed
        limit = MAX_ADU if MAX_ADU < avail else avail
        found = scan_crc(p, n, pos, limit) if limit >= MIN_ADU else 0
        if found:
            crossed = self._crosses_frames(p, pos, pos + found, n, mode)
            if crossed < 0:
                return WAIT
            if not crossed:
                self.d_resp = resp
                return found
            self.d_reason = _CROSSED
            return SKIP
        if avail < MAX_ADU and mode != FINAL:
            # no silence mark: pos >= mark always holds
            if self._lined_up(p, pos, n, mode, pos + MAX_ADU, awaited, True) != 1:
                return WAIT
        return -3

    cdef Py_ssize_t _decide_boundary(self, const unsigned char* p, Py_ssize_t pos, Py_ssize_t n, int mode,
                                     int nread, int r0, int r1) except -2:
        """``RtuDecoder._decide_boundary``: a length, WAIT, or -3 (go on to noise)."""
        cdef Py_ssize_t found, plen
        cdef int i, resp
        found = self._boundary(p, pos, n, mode)
        if found < 0:
            return WAIT  # may_go_on is False outside a silence
        if not found:
            return -3
        for i in range(nread):
            resp = r0 if i == 0 else r1
            plen = pdu_len(p, pos + 1, found - 1, resp)
            if plen != NO_LENGTH and plen != NEED_MORE and plen + 3 == found:
                self.d_resp = resp
                return found
        self.d_resp = r0
        return found

    cdef Py_ssize_t _standalone(self, const unsigned char* p, Py_ssize_t k, Py_ssize_t n, int mode) except -2:
        """``RtuBounds._standalone``: length of a frame of predictable length with a valid
        CRC at ``k``, 0 none, -1 the bytes to tell are missing (STREAM)."""
        cdef Py_ssize_t avail = n - k, total, at, plen, m
        cdef int fc, r, kind
        cdef bint short = False
        if avail < 2:
            return -1 if mode == STREAM else 0
        fc = p[k + 1]
        if fc == 0 or fc == 0x80:
            return 0
        if not EXC0_STANDALONE and fc & 0x80 and avail > 2 and not p[k + 2]:
            return 0  # an exception answer with exception code 0 (the reference's rule)
        for r in range(2):
            if not (self.allow_resp if r else self.allow_req):
                continue
            if fc & 0x80 and not r:
                continue
            kind = ADU_KIND[r][fc]
            if kind == 1:
                total = ADU_A[r][fc]
            elif kind == 2:
                at = k + ADU_A[r][fc]
                if at >= n:
                    short = True
                    continue
                total = ADU_B[r][fc] + p[at]
            else:
                m = avail - 1 if avail - 1 < PEEK else PEEK
                plen = pdu_len(p, k + 1, m, r)
                if plen == NEED_MORE and avail - 1 > PEEK:
                    m = avail - 1 if avail - 1 < MAX_ADU - 1 else MAX_ADU - 1
                    plen = pdu_len(p, k + 1, m, r)
                if plen == NO_LENGTH:
                    continue
                if plen == NEED_MORE:
                    short = True
                    continue
                if plen < 1:
                    continue
                total = plen + 3
            if total > MAX_ADU:
                continue
            if total > avail:
                short = True
            elif crc_ok(p, n, k, k + total):
                return total
        return -1 if short and mode == STREAM else 0

    cdef Py_ssize_t _next_frame(self, const unsigned char* p, Py_ssize_t pos, Py_ssize_t n, int mode,
                                Py_ssize_t* length) except -2:
        """``RtuBounds._next_frame``: the first offset after ``pos`` where a frame of its own
        starts (``length`` its length), or where the search stopped (``length`` 0)."""
        cdef Py_ssize_t stop = n if n < pos + MAX_ADU + 1 else pos + MAX_ADU + 1
        cdef Py_ssize_t start = pos + 1, lo, k, found = 0
        cdef bint broke = False
        if self.has_near and self.near_lo <= pos < self.near_k:
            if self.near_found:
                length[0] = self.near_found
                return self.near_k
            start = self.near_k
            lo = self.near_lo
        else:
            lo = pos
        k = start
        while k < stop:
            found = self._standalone(p, k, n, mode)
            if found > 0:
                broke = True
                break
            k += 1
        if not broke:
            found = 0
        self.has_near = True
        self.near_lo, self.near_k, self.near_found = lo, k, found
        length[0] = found
        return k

    cdef int _lined_up(self, const unsigned char* p, Py_ssize_t pos, Py_ssize_t n, int mode, Py_ssize_t far,
                       bint fits, bint within) except -2:
        """``RtuBounds._lined_up`` without a silence mark: 1 yes, 0 no, -1 cannot tell yet.
        ``fits`` and ``within`` change nothing without a silence but the memo's key
        (when the reference keys it so)."""
        cdef Py_ssize_t k, length, first, stop, end, after, unsure = -1
        cdef int state = 0
        cdef bint seen = False, broke = False
        if (
            self.has_lined
            and self.lined_lo <= pos < self.lined_first
            and (not MEMO_KEYED or (self.lined_fits == fits and self.lined_within == within))
        ):
            k, state = self.lined_k, self.lined_state
            if state:
                return state if k < far else 0
            if far <= k:
                return 0
            state = 0
        k = self._next_frame(p, pos, n, mode, &length)
        first = k
        stop = far if far < n else n
        while length and k < stop:
            end = k + length
            if seen or (mode != STREAM and end == n):
                state = 1
                broke = True
                break
            after = self._standalone(p, end, n, mode)
            if after > 0:
                state = 1
                broke = True
                break
            if after and unsure < 0:
                unsure = k
            seen = True
            k += 1
            length = 0
            while k < stop:
                length = self._standalone(p, k, n, mode)
                if length > 0:
                    break
                length = 0
                k += 1
        if not broke:
            k = stop
        if not state and unsure >= 0:
            k, state = unsure, -1
        self.has_lined = True
        self.lined_lo, self.lined_first, self.lined_k, self.lined_state = pos, first, k, state
        self.lined_fits, self.lined_within = fits, within
        return state if k < far else 0

    cdef Py_ssize_t _boundary(self, const unsigned char* p, Py_ssize_t pos, Py_ssize_t n, int mode) except -2:
        """``RtuBounds.boundary`` without a silence mark."""
        cdef Py_ssize_t length, k, end
        k = self._next_frame(p, pos, n, mode, &length)
        if length:
            end = k
        elif mode != STREAM and n <= k:
            end = n
        else:
            end = -1
        if end >= 0 and end - pos >= MIN_ADU and crc_ok(p, n, pos, end):
            return end - pos
        if not length and mode == STREAM and k >= n:
            return -1
        return 0

    cdef int _crosses_frames(self, const unsigned char* p, Py_ssize_t start, Py_ssize_t end, Py_ssize_t n, int mode) except -2:
        """``RtuBounds.crosses_frames`` without a silence mark: 1, 0, -1."""
        cdef Py_ssize_t j, first, second
        for j in range(start + 1, end):
            first = self._standalone(p, j, n, mode)
            if first < 0:
                return -1
            if not first:
                continue
            if j + first >= end:
                return 1
            second = self._standalone(p, j + first, n, mode)
            if second < 0:
                return -1
            if second:
                return 1
        return 0
