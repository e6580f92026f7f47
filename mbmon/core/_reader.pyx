# cython: language_level=3, boundscheck=True, wraparound=False, cdivision=True
"""The compiled core of ``mbmon read``: capture bytes in, console lines out.

One fused loop does what the reference pipeline does for the cases it covers
(pcap/pcapng records -> link layer -> IPv4 -> TCP reassembly -> MBAP framing ->
pairing and timeouts -> the text or JSON line in one growing buffer), with the
same rules as :mod:`mbmon.sources.pcapfile`, :mod:`mbmon.sources.dissect`,
:mod:`mbmon.sources.tcpflow`, :mod:`mbmon.protocol.mbap`,
:mod:`mbmon.protocol.pairing` and :mod:`mbmon.pipeline`. Anything outside them
raises :class:`Declined`; :func:`read_capture_core` runs the loop twice, a
first pass that only decides (nothing is written) and, when nothing declined,
a second pass that writes, so a decline always comes before the first byte.

Lines of the common PDUs (well-formed 01-06, 0F, 10 and exceptions) are made
here; every other record (events, other function codes, malformed PDUs) is
built as the reference pipeline's :class:`~mbmon.model.Record` and formatted by
:mod:`mbmon.format` itself, so it is the same by construction.

With an MCAP log (``_Pass.log_to``), the writing pass also makes the log's message
records, byte for byte those ``mbmon.io.mcap.layout.LogLayout.convert`` makes (see
"MCAP messages" in ``_Pass``).

Memory safety: the file is a bounds-checked typed memoryview; every header is
checked against the bytes present before it is read through a pointer.
"""

from libc.stdlib cimport malloc, realloc, free
from libc.string cimport memchr, memcmp, memcpy, memmove, memset, strlen
from libc.math cimport floor, isfinite, fabs, nextafter, INFINITY
from libc.math cimport frexp, ldexp, signbit, copysign
from libc.math cimport rint, NAN
from libc.stdlib cimport strtod
from libc.stdint cimport uint8_t, uint32_t, uint64_t, int64_t

cdef extern from "Python.h":
    char* PyOS_double_to_string(double val, char format_code, int precision,
                                int flags, int *ptype) except NULL
    double PyOS_string_to_double(const char *s, char **endptr,
                                 object overflow_exception) except? -1.0
    void PyMem_Free(void *p)
    int Py_DTSF_ADD_DOT_0

from cpython.bytes cimport PyBytes_FromStringAndSize, PyBytes_AS_STRING, _PyBytes_Resize
from cpython.ref cimport PyObject, Py_INCREF, Py_DECREF, Py_XDECREF
from cpython.unicode cimport PyUnicode_DecodeUTF8
from cpython.exc cimport PyErr_CheckSignals

import orjson as _orjson
import signal as _signal_mod
import threading as _threading
import sys as _sys

from mbmon.format import function_name, exception_name, record_line
from mbmon.jsonfmt import record_json_bytes
from mbmon.model import (
    Direction, Event, EventKind, Frame, Record, RecordKind, Stream, Transport,
)
from mbmon.model import Chunk
_FRAME_KINDS = (RecordKind.REQUEST, RecordKind.RESPONSE, RecordKind.EXCEPTION)
from mbmon.io.mcap.proto import encode_frame as _encode_frame
from mbmon.model import Kind, Transaction, TxStatus
from mbmon.protocol.pairing import _needs_request
from mbmon.protocol.pdu import decode_pdu
from mbmon.model import Noise
from mbmon.protocol.mbap import DEFAULT_MAX_LENGTH as _MBAP_MAX, MbapDecoder
from mbmon.protocol.pdu import with_malformed
from mbmon.sources.flows import _TCP_HOLD_LIMIT, address_text
from mbmon.sources.tcpflow import TcpConnection, TcpStats


class Declined(Exception):
    """The input has something the core does not cover; the message says what."""


class Enough(Exception):
    """``-c N``: the N-th frame the filters let through was written; the run ends there
    (the reference's ``FrameBudget`` cuts every output after it, the summary too)."""


DEF MAX_ACK_JUMP = 1 << 24
DEF REUSE_DISTANCE = 1 << 20
DEF CLOSED_LINGER = 60.0
DEF MAX_CLOSED = 4096
DEF MAX_OPEN = 9000            # the dissector evicts at 10,000 open connections
DEF MAX_UDP = 9000             # ... and at 10,000 UDP pairs
DEF MAX_PENDING_STREAM = 9000  # the pairer evicts at 10,000 per stream
DEF MAX_PENDING_TOTAL = 90000  # ... and 100,000 in all
DEF TICK_EVERY = 0.1
DEF MAX_RECORD = 1 << 26
DEF FLUSH_AT = 1 << 20
DEF BLOCK_ROOM = FLUSH_AT + (1 << 17)  # a log block's bytes object: a block and its last item
DEF HAND_WHOLE = FLUSH_AT >> 1  # a block this long is handed over as it is, not copied
DEF RELEASE_EVERY = 1 << 24  # a multiple of every page size
DEF UDP_PORT_KEY = 0x10000    # dissect._UDP_PORT: a UDP port's key in the port counts
DEF MAX_PORTS = 4096          # dissect.MAX_PORTS: distinct other ports counted
DEF MBAP_CLEAN = 254          # the largest clean MBAP length (mbap.DEFAULT_MAX_LENGTH)

if _MBAP_MAX != MBAP_CLEAN:
    raise ImportError("the core's MBAP length limit is not the reference's")

cdef int FIN = 0x01, SYN = 0x02, RST = 0x04, ACK = 0x10
# 32-bit sequence arithmetic as C constants (a literal above C int range is a Python int)
cdef int64_t MASK = 0xFFFFFFFF
cdef int64_t HALF = 0x80000000
cdef int64_t TWO32 = 0x100000000

# --------------------------------------------------------------------------- helpers


cdef inline int64_t signed32(int64_t diff) noexcept:
    diff &= MASK
    return diff - TWO32 if diff & HALF else diff


cdef inline uint32_t be16(const uint8_t* p) noexcept:
    return (<uint32_t>p[0] << 8) | p[1]


cdef inline uint32_t be32(const uint8_t* p) noexcept:
    return (<uint32_t>p[0] << 24) | (<uint32_t>p[1] << 16) | (<uint32_t>p[2] << 8) | p[3]


cdef inline uint32_t le32(const uint8_t* p) noexcept:
    return (<uint32_t>p[3] << 24) | (<uint32_t>p[2] << 16) | (<uint32_t>p[1] << 8) | p[0]


cdef inline uint32_t rd32(const uint8_t* p, bint big) noexcept:
    return be32(p) if big else le32(p)


cdef inline uint32_t rd16(const uint8_t* p, bint big) noexcept:
    return ((<uint32_t>p[0] << 8) | p[1]) if big else ((<uint32_t>p[1] << 8) | p[0])


cdef const char* HEXD = b"0123456789ABCDEF"

# "00" to "99": decimal digits two a division (register values are most of a line's
# digits; a 200-byte table stays in L1, where a table of every 16-bit value's text,
# 384 KiB, missed the cache on most values next to the log's compression)
cdef char DIG2[200]


cdef void _fill_dig2() noexcept:
    cdef int v
    for v in range(100):
        DIG2[2 * v] = <char>(48 + v // 10)
        DIG2[2 * v + 1] = <char>(48 + v % 10)


_fill_dig2()


cdef inline int u16_text(char* o, unsigned int v) noexcept:
    """The decimal digits of ``v`` (below 65536) into ``o`` (room for five): how many."""
    cdef unsigned int hi, r
    if v < 10:
        o[0] = <char>(48 + v)
        return 1
    if v < 100:
        o[0] = DIG2[2 * v]
        o[1] = DIG2[2 * v + 1]
        return 2
    if v < 10000:
        hi = v // 100
        r = (v % 100) * 2
        if hi < 10:
            o[0] = <char>(48 + hi)
            o[1] = DIG2[r]
            o[2] = DIG2[r + 1]
            return 3
        o[0] = DIG2[2 * hi]
        o[1] = DIG2[2 * hi + 1]
        o[2] = DIG2[r]
        o[3] = DIG2[r + 1]
        return 4
    o[0] = <char>(48 + v // 10000)
    v %= 10000
    hi = (v // 100) * 2
    r = (v % 100) * 2
    o[1] = DIG2[hi]
    o[2] = DIG2[hi + 1]
    o[3] = DIG2[r]
    o[4] = DIG2[r + 1]
    return 5


cdef inline int put_u16(Buf* b, unsigned int v) except -1:
    if b.n + 5 > b.cap:
        buf_need(b, 5)
    b.n += u16_text(b.p + b.n, v & 0xFFFF)
    return 0


cdef struct Buf:
    char* p
    Py_ssize_t n
    Py_ssize_t cap
    # NULL: ``p`` is the C library's (malloc); else a bytes object of ``cap`` bytes
    # whose storage ``p`` is, owned here until handed over whole (``box_take``)
    PyObject* box


cdef int buf_need(Buf* b, Py_ssize_t more) except -1:
    cdef Py_ssize_t cap
    cdef char* p
    if b.n + more <= b.cap:
        return 0
    cap = b.cap * 2 if b.cap else 1 << 16
    while cap < b.n + more:
        cap *= 2
    if b.box != NULL:
        return box_grow(b, cap)
    p = <char*>realloc(b.p, cap)
    if p == NULL:
        raise MemoryError()
    b.p = p
    b.cap = cap
    return 0


cdef int box_new(Buf* b, Py_ssize_t cap) except -1:
    """Make ``b`` (empty, holding nothing) a fresh bytes object of ``cap`` bytes: what is
    written into it is handed over later without a copy (:func:`box_take`)."""
    o = PyBytes_FromStringAndSize(NULL, cap)  # its bytes are written before anyone sees them
    b.box = <PyObject*>o
    Py_INCREF(o)  # the reference ``box`` holds
    b.p = PyBytes_AS_STRING(o)
    b.n = 0
    b.cap = cap
    return 0


cdef int box_grow(Buf* b, Py_ssize_t cap) except -1:
    """A boxed ``b`` with room for ``cap`` bytes: a larger bytes object with what was
    written copied in (rare: an item longer than the block's spare room). The old one
    stays ``b``'s if the new one cannot be made."""
    o = PyBytes_FromStringAndSize(NULL, cap)
    memcpy(PyBytes_AS_STRING(o), b.p, b.n)
    Py_DECREF(<object>b.box)
    b.box = <PyObject*>o
    Py_INCREF(o)
    b.p = PyBytes_AS_STRING(o)
    b.cap = cap
    return 0


cdef bytes box_take(Buf* b):
    """What was written into a boxed ``b``, as the bytes object it was written in (cut to
    its length in place: ``_PyBytes_Resize`` of a sole reference, no copy); ``b`` is left
    empty and holding nothing (plain, until :func:`box_new`)."""
    cdef PyObject* box = b.box
    cdef Py_ssize_t n = b.n
    b.box = NULL
    b.p = NULL
    b.n = 0
    b.cap = 0
    _PyBytes_Resize(&box, n)  # a failure frees it (never when shrinking on glibc)
    data = <bytes>box  # a new reference; the box's own is given up below
    Py_DECREF(data)
    return data


cdef void buf_free(Buf* b) noexcept:
    """Free what ``b`` holds (its bytes object when boxed)."""
    if b.box != NULL:
        Py_XDECREF(b.box)
        b.box = NULL
    else:
        free(b.p)
    b.p = NULL
    b.n = 0
    b.cap = 0


cdef inline int put(Buf* b, const char* s, Py_ssize_t n) except -1:
    if b.n + n > b.cap:
        buf_need(b, n)
    memcpy(b.p + b.n, s, n)
    b.n += n
    return 0


cdef inline int put_bytes(Buf* b, bytes s) except -1:
    return put(b, s, len(s))


cdef inline int put_c(Buf* b, char c) except -1:
    if b.n + 1 > b.cap:
        buf_need(b, 1)
    b.p[b.n] = c
    b.n += 1
    return 0


cdef inline void varint_in_room(Buf* b, uint64_t v) noexcept:
    """``v`` as a protobuf varint, in room the caller has made (at most 10 bytes)."""
    while v > 0x7F:
        b.p[b.n] = <char>((v & 0x7F) | 0x80)
        b.n += 1
        v >>= 7
    b.p[b.n] = <char>v
    b.n += 1


cdef inline void c_in_room(Buf* b, char c) noexcept:
    """One byte, in room the caller has made."""
    b.p[b.n] = c
    b.n += 1


cdef inline void put_in_room(Buf* b, const char* s, Py_ssize_t n) noexcept:
    """``n`` bytes, in room the caller has made."""
    memcpy(b.p + b.n, s, n)
    b.n += n


cdef int put_varint(Buf* b, uint64_t v) except -1:
    """``v`` as a protobuf varint."""
    if b.n + 10 > b.cap:
        buf_need(b, 10)
    varint_in_room(b, v)
    return 0


cdef int put_f64(Buf* b, double v) except -1:
    """``v`` as a protobuf double (little-endian IEEE 754)."""
    if b.n + 8 > b.cap:
        buf_need(b, 8)
    memcpy(b.p + b.n, &v, 8)  # x86-64 and arm64: little-endian
    b.n += 8
    return 0


cdef int put_packed_words(Buf* b, const uint8_t* words, int count) except -1:
    """Big-endian 16-bit words as a packed varint field's length and body."""
    cdef int i, size = 0
    cdef unsigned int v
    for i in range(count):
        v = be16(words + 2 * i)
        size += 1 if v < 0x80 else (2 if v < 0x4000 else 3)
    put_varint(b, <uint64_t>size)
    buf_need(b, size)
    for i in range(count):
        varint_in_room(b, be16(words + 2 * i))
    return 0


cdef int put_u(Buf* b, uint64_t v) except -1:
    """``v``'s decimal digits, two a division (``DIG2``)."""
    cdef char tmp[20]
    cdef int i = 20
    cdef unsigned int r
    if v < 65536:
        return put_u16(b, <unsigned int>v)
    while v >= 100:
        r = <unsigned int>(v % 100) * 2
        v //= 100
        i -= 2
        tmp[i] = DIG2[r]
        tmp[i + 1] = DIG2[r + 1]
    if v >= 10:
        r = <unsigned int>v * 2
        i -= 2
        tmp[i] = DIG2[r]
        tmp[i + 1] = DIG2[r + 1]
    else:
        i -= 1
        tmp[i] = <char>(48 + v)
    return put(b, tmp + i, 20 - i)


cdef int put_i(Buf* b, int64_t v) except -1:
    if v < 0:
        put_c(b, 45)
        return put_u(b, <uint64_t>(-v))
    return put_u(b, <uint64_t>v)


cdef int put_hex(Buf* b, const uint8_t* p, Py_ssize_t n) except -1:
    """``n`` bytes as upper-case hex pairs separated by single spaces."""
    cdef Py_ssize_t i
    cdef char* o
    if n <= 0:
        return 0
    buf_need(b, 3 * n)
    o = b.p + b.n
    for i in range(n):
        o[0] = HEXD[p[i] >> 4]
        o[1] = HEXD[p[i] & 15]
        o[2] = 32
        o += 3
    b.n += 3 * n - 1
    return 0


cdef int64_t scaled_round(double v, uint64_t scale) noexcept nogil:
    """``|v| * scale`` rounded to an integer as CPython's correctly rounded formatting
    rounds it (``scale`` a power of ten up to 1000), or -1 when ``v`` is outside what
    this proves (non-finite, |v| >= 2^40: the caller asks CPython).

    ``|v| = f * 2^e`` with ``m = f * 2^53`` an integer below 2^53 (frexp and ldexp are
    exact), so ``|v| * scale = m * scale / 2^(53 - e)`` exactly, ``m * scale`` below
    2^63; the quotient rounded by its remainder, a half to even (dtoa's rule for an
    exact tie), is the decimal CPython writes and reads back."""
    cdef int e, s
    cdef uint64_t big, q, rem, half
    if not (fabs(v) < 1099511627776.0):
        return -1
    big = <uint64_t>ldexp(frexp(fabs(v), &e), 53) * scale
    s = 53 - e  # >= 13 below 2^40
    if s >= 64:
        return 0  # big < 2^63: below a half
    q = big >> s
    rem = big & ((<uint64_t>1 << s) - 1)
    half = <uint64_t>1 << (s - 1)
    if rem > half or (rem == half and (q & 1)):
        q += 1
    return <int64_t>q


cdef int fixed_text(char* out, double v, int precision) noexcept nogil:
    """``'%.Nf' % v`` (N = ``precision``, 0..3) into ``out`` (at least 24 bytes), exactly
    as CPython writes it (``scaled_round``'s digits), without the dtoa round trip; its
    length, or -1 where ``scaled_round`` proves nothing. The sign is the double's own
    (``-0.0`` and what rounds to zero from below write ``-0.0``, as CPython does)."""
    cdef int n = 0, i
    cdef uint64_t scale = 1, whole, frac
    cdef int64_t q
    cdef char tmp[24]
    if precision < 0 or precision > 3:
        return -1
    for i in range(precision):
        scale *= 10
    q = scaled_round(v, scale)
    if q < 0:
        return -1
    if signbit(v):
        out[n] = 45
        n += 1
    whole = <uint64_t>q // scale
    frac = <uint64_t>q % scale
    i = 24
    while True:
        i -= 1
        tmp[i] = <char>(48 + whole % 10)
        whole //= 10
        if whole == 0:
            break
    memcpy(out + n, tmp + i, 24 - i)
    n += 24 - i
    if precision:
        out[n] = 46
        for i in range(precision, 0, -1):
            out[n + i] = <char>(48 + frac % 10)
            frac //= 10
        n += precision + 1
    return n


cdef double round3_exact(double v) noexcept nogil:
    """``round(v, 3)`` where ``scaled_round`` proves it (else NaN): the double nearest
    the correctly rounded three decimals, ``q / 1000`` (q below 2^53: one correctly
    rounded division, as strtod reads the digits back), with ``v``'s sign."""
    cdef int64_t q = scaled_round(v, 1000)
    if q < 0:
        return NAN
    return copysign(<double>q / 1000.0, v)


cdef int put_double(Buf* b, double v, char code, int precision, int flags) except -1:
    """``v`` formatted by CPython's own float formatting (repr 'r', or 'f'); 'f' with up
    to three decimals is written here (``fixed_text``: the same digits, proved)."""
    cdef char* s
    cdef Py_ssize_t n = 0
    if code == 102 and flags == 0:
        if b.n + 24 > b.cap:
            buf_need(b, 24)
        n = fixed_text(b.p + b.n, v, precision)
        if n >= 0:
            b.n += n
            return 0
        n = 0
    s = PyOS_double_to_string(v, code, precision, flags, NULL)
    while s[n]:
        n += 1
    try:
        put(b, s, n)
    finally:
        PyMem_Free(s)
    return 0


cdef int put_json_float(Buf* b, double v) except -1:
    """``orjson.dumps(v)``: CPython's repr where the two agree, orjson itself elsewhere."""
    cdef double a = fabs(v)
    if isfinite(v) and (a == 0.0 or (1e-4 <= a < 1e16)):
        return put_double(b, v, b'r', 0, Py_DTSF_ADD_DOT_0)
    return put_bytes(b, _orjson.dumps(v))


cdef int put_trimmed(Buf* b, char* s, Py_ssize_t n) except -1:
    """A fixed-point number without its trailing zeros (one digit stays after the point)."""
    while n > 2 and s[n - 1] == 48 and s[n - 2] != 46:
        n -= 1
    return put(b, s, n)


cdef int put_json_time(Buf* b, double ts) except -1:
    """``orjson.dumps(ts)`` of a capture time: its microseconds' decimal text, trimmed,
    when that text reads back as ``ts`` (then, below 2^33 s, no shorter text does and
    it is the shortest repr); CPython's repr otherwise."""
    cdef double whole, x
    cdef int64_t us, sec
    cdef char tmp[40]
    cdef int i, n
    cdef char* end
    cdef int verdict
    if 0.0 <= ts < 8589934592.0:
        whole = floor(ts)
        x = (ts - whole) * 1e6 + 0.5
        us = 999999 if x > 999999.0 else <int64_t>x
        sec = <int64_t>whole
        n = 0
        if sec == 0:
            tmp[0] = 48
            n = 1
        else:
            i = 20
            while sec:
                i -= 1
                tmp[i] = <char>(48 + sec % 10)
                sec //= 10
            n = 20 - i
            memmove(tmp, tmp + i, n)
        tmp[n] = 46
        for i in range(6, 0, -1):
            tmp[n + i] = <char>(48 + us % 10)
            us //= 10
        n += 7
        tmp[n] = 0
        verdict = round_trips(ts, whole, <double>(<int64_t>x if x <= 999999.0 else 999999))
        if verdict > 0 or (verdict == 0 and strtod(tmp, &end) == ts):
            return put_trimmed(b, tmp, n)
    return put_json_float(b, ts)


cdef int round_trips(double ts, double whole, double us):
    """Whether the decimal ``whole + us / 1e6`` reads back as ``ts``: 1 yes, -1 no, 0 too
    close to call (the caller asks strtod). ``ts - whole`` is exact; the error of the
    computed difference is below 1e-15, kept as a margin on each side."""
    cdef double e = us * 1e-6 - (ts - whole)
    cdef double half
    if e >= 0:
        half = (nextafter(ts, INFINITY) - ts) / 2
    else:
        half = (ts - nextafter(ts, -INFINITY)) / 2
        e = -e
    if e < half - 1e-15:
        return 1
    if e > half + 1e-15:
        return -1
    return 0


cdef int put_json_round3(Buf* b, double v) except -1:
    """``orjson.dumps(round(v, 3))``: CPython's correctly rounded three decimals, trimmed
    (below 1e9 no shorter text reads back as that float); ``fixed_text``'s digits where
    it proves them."""
    cdef char tmp[24]
    cdef char* s
    cdef Py_ssize_t n = fixed_text(tmp, v, 3)
    if n >= 0:
        return put_trimmed(b, tmp, n)
    s = PyOS_double_to_string(v, b'f', 3, 0, NULL)
    n = 0
    while s[n]:
        n += 1
    try:
        put_trimmed(b, s, n)
    finally:
        PyMem_Free(s)
    return 0


cdef double py_round3(double v) except? -1.0:
    """``round(v, 3)``: ``round3_exact`` where it proves it, else CPython's correctly
    rounded digits, read back."""
    cdef double r = round3_exact(v)
    if r == r:
        return r
    cdef char* s = PyOS_double_to_string(v, b'f', 3, 0, NULL)
    try:
        r = PyOS_string_to_double(s, NULL, None)
    finally:
        PyMem_Free(s)
    return r


# --------------------------------------------------------------------------- MCAP


#: capture times (s) whose log time a message record holds (``layout._MAX_TS``, from
#: ``writer.MAX_LOG_TIME``: 2**64 - 1 ns)
cdef double MAX_TS = ((1 << 64) - 1) // 1000 / 1_000_000 - 1.0


cdef inline void put_le(char* p, uint64_t v, int n) noexcept:
    cdef int i
    for i in range(n):
        p[i] = <char>(v & 255)
        v >>= 8


cdef inline void put_head(char* p, Py_ssize_t size, int channel, uint64_t log_time) noexcept:
    """An MCAP message record's head (``writer.MESSAGE_HEAD``: opcode 5, its length,
    channel, sequence 0, log and publish time) for ``size`` bytes of data."""
    p[0] = 5
    put_le(p + 1, <uint64_t>(22 + size), 8)
    put_le(p + 9, <uint64_t>channel, 2)
    put_le(p + 11, 0, 4)
    put_le(p + 15, log_time, 8)
    put_le(p + 23, log_time, 8)


cdef inline bint _name_char(char c) nogil:
    return (c >= 97 and c <= 122) or c == 95  # a-z, _


cdef Py_ssize_t slim_frame(char* p, Py_ssize_t n, Py_ssize_t cut_at, Py_ssize_t cut_end):
    """A frame's JSON line made its format-2 /modbus/frames message in place
    (``layout.slim_frame_json``): ``p[cut_at:cut_end]`` (the line member) cut out, and
    every member ``,"name":null`` followed by ``,`` or ``}`` left out, up to the first
    ``,"fields":`` (the nested member keeps its own). Returns the new length.

    It looks at each colon (``memchr``) outside the line: a member's name is lower-case
    letters and ``_`` between ``,"`` and ``":``, and a string's own quotes are escaped,
    so a colon inside a string never passes for one. Each byte kept moves once."""
    cdef Py_ssize_t o = 0, src = 0, i = 0, k, lim
    cdef bint cut = False
    cdef const char* c
    while True:
        lim = n if cut else cut_at
        c = <const char*>memchr(p + i, 58, lim - i)  # ':'
        if c == NULL:
            if cut:
                break
            if o != src:
                memmove(p + o, p + src, cut_at - src)
            o += cut_at - src
            src = i = cut_end
            cut = True
            continue
        i = c - p
        if (i + 5 < n and (cut or i + 5 <= cut_at) and p[i + 1] == 110
                and memcmp(p + i + 1, b"null", 4) == 0 and (p[i + 5] == 44 or p[i + 5] == 125)):
            k = i - 1
            if k > src and p[k] == 34:  # the closing quote of a name?
                while k > src and _name_char(p[k - 1]):
                    k -= 1
                if (k < i - 1 and k - 2 >= src and p[k - 1] == 34
                        and p[k - 2] == 44):  # ,"name":
                    k -= 2  # the member starts at its comma
                    if o != src:
                        memmove(p + o, p + src, k - src)
                    o += k - src
                    src = i + 5
        elif cut and p[i - 1] == 34 and memcmp(p + i - 9, b',"fields"', 9) == 0:
            break
        i += 1
    if not cut:
        if o != src:
            memmove(p + o, p + src, cut_at - src)
        o += cut_at - src
        src = cut_end
    if o != src:
        memmove(p + o, p + src, n - src)
    return o + n - src


# --------------------------------------------------------------------------- state


cdef struct Half:
    int64_t nxt            # next expected sequence number; -1: none yet
    int64_t isn            # from the SYN; -1: none
    int64_t fin            # sequence number of the FIN; -1: none
    bint done              # FIN reached in order
    uint8_t* buf           # MBAP bytes held (an ADU not complete yet)
    int blen
    int bcap
    double bts             # when the first byte held arrived (the decoder's _buf_ts)
    uint8_t dstate         # the pipeline's decoder of this direction: 0 none yet (no
    #                        bytes came), 1 framed here, 2 by the reference MbapDecoder
    #                        (noise: see ref_chunk)


cdef struct Conn:
    int sid
    Half h[2]              # 0: client to server, 1: server to client
    bint connected
    bint closed
    bint open_             # in the dissector's open connections
    bint tref              # the reference TcpConnection reassembles it (see ref_segment)
    int fin_by             # 0 none, 1 client, 2 server
    uint8_t caddr[16]      # IPv4: the first 4 bytes
    uint8_t saddr[16]
    int alen               # address length: 4 (IPv4) or 16 (IPv6)
    bint udp               # a UDP pair (Modbus/UDP), not a TCP connection
    int cport
    int sport


cdef struct Pend:
    double ts
    int64_t index          # the request's record index
    uint64_t key
    int sid
    int tid
    int unit
    int fc
    int prev               # the stream's pending requests, oldest first
    int next
    int alen
    uint8_t raw[262]


cdef struct SPend:        # one stream's pending requests
    int head
    int tail
    int count
    int aprev              # streams with pending requests, in the pairer's dict order
    int anext
    bint active


cdef struct Native:       # a PDU this module formats itself
    int kind               # 0 request, 1 response, 2 exception
    int fc
    int has_addr
    int address
    int count              # -1: none
    int nvalues            # -1: values null
    int bits               # values are bits (else registers)
    const uint8_t* vdata   # registers: big-endian words; bits: packed bytes
    int exc                # exception code, -1 none
    int onoff              # 05: the note says ON/OFF



# --------------------------------------------------------------------------- profiles


cdef struct Op:           # one operation of a compiled read (mbmon.semantics.profile.compiled)
    int kind               # 0: one value, 1: a run of plain words
    int a                  # first word
    int b                  # end word
    int type               # 0 u16, 1 s16, 2 u32, 3 i32, 4 f32
    int high_low           # two-word types: the high word first
    int fmt                # F_PLAIN .. F_FLOAT
    int decimals
    int64_t divisor
    double scale
    int has_range
    int64_t lo
    int64_t hi
    int head               # texts[head]: "A1 = "
    int suffix             # texts[suffix]: " mm"
    int enum               # enums[enum]: value -> text, or -1


cdef class _CRead:
    """One read request shape of one profile, compiled: the request's notes and the
    operations writing its answer's notes (``nops < 0``: the annotator writes them)."""

    cdef list req_notes         # the request's notes, as written (UTF-8, JSON-escaped in JSON)
    cdef Op* ops
    cdef int nops
    cdef list texts
    cdef list enums             # per enum: dict value -> text as written

    def __cinit__(self):
        self.ops = NULL
        self.nops = -1

    def __dealloc__(self):
        free(self.ops)


cdef class _Bound:
    """A profile bound to a server and unit, its session (or None) and what the session
    watches (:class:`mbmon.semantics.session.CoreWatch`)."""

    cdef object profile
    cdef object session
    cdef dict reads             # (fc << 32) | (address << 16) | count -> _CRead
    cdef double deadline
    cdef object watch           # the CoreWatch the arrays below hold
    cdef int nw                 # watched answer ranges; -1: every answer
    cdef int wfc[64]
    cdef int wfirst[64]
    cdef int wlast[64]
    cdef int wlo[64]
    cdef int whi[64]

    def __init__(self, profile, session):
        self.profile = profile
        self.session = session
        self.reads = {}
        self.deadline = INFINITY
        self.nw = 0

    cdef int refresh(self) except -1:
        """Ask the session again what it watches (after every call into it)."""
        cdef int i = 0
        if self.session is None:
            return 0
        watch = self.session.core_watch()
        if watch is self.watch:
            return 0
        self.watch = watch
        self.deadline = watch.deadline
        if len(watch.answers) > 64:
            self.nw = -1
            return 0
        for fc, first, last, lo, hi in watch.answers:
            self.wfc[i] = fc
            self.wfirst[i] = first
            self.wlast[i] = last
            self.wlo[i] = lo
            self.whi[i] = hi
            i += 1
        self.nw = i
        return 0

    cdef bint watched(self, int fc, int address, int count, const uint8_t* words):
        """Whether an answer (``count`` big-endian ``words`` read at ``address``) goes
        to the session."""
        cdef int i, lo, hi, r, v
        if self.nw < 0:
            return True
        for i in range(self.nw):
            if self.wfc[i] != fc:
                continue
            lo = self.wfirst[i] if self.wfirst[i] > address else address
            hi = self.wlast[i] if self.wlast[i] < address + count - 1 else address + count - 1
            if lo > hi:
                continue
            if self.wlo[i] > self.whi[i]:
                return True
            for r in range(lo, hi + 1):
                v = <int>be16(words + 2 * (r - address))
                if v & 0x8000:
                    v -= 0x10000
                if v < self.wlo[i] or v > self.whi[i]:
                    return True
        return False


cdef bytes _note_bytes(str text, bint as_json):
    """A note as the line carries it: UTF-8 (as the console writes it), JSON-escaped in JSON."""
    if as_json:
        return _inner(_orjson.dumps(text))
    return text.encode("utf-8", "backslashreplace")


cdef _CRead _compile_read(object profile, int fc, int address, int count, bint as_json):
    """:func:`mbmon.semantics.profile.compiled.compile_read` as the core keeps it."""
    from mbmon.semantics.profile.compiled import compile_read, compile_write_answer

    cdef _CRead cr = _CRead()
    cdef Op* op
    cdef int i
    if fc & 0x100:  # the answer to a register write
        compiled = compile_write_answer(profile, fc & 0xFF, address, count)
    else:
        compiled = compile_read(profile, fc, address, count)
    cr.req_notes = [_note_bytes(n, as_json) for n in compiled.request]
    cr.texts = []
    cr.enums = []
    if compiled.answer is None:
        return cr
    cr.ops = <Op*>malloc((len(compiled.answer) + 1) * sizeof(Op))
    if cr.ops == NULL:
        raise MemoryError()
    for i, item in enumerate(compiled.answer):
        (kind, a, b, type_, high_low, fmt, decimals, divisor, scale, rng, head, suffix,
         enum) = item
        op = &cr.ops[i]
        op.kind = kind
        op.a = a
        op.b = b
        op.type = type_
        op.high_low = 1 if high_low else 0
        op.fmt = fmt
        op.decimals = decimals
        op.divisor = divisor
        op.scale = scale
        op.has_range = rng is not None
        op.lo = rng[0] if rng is not None else 0
        op.hi = rng[1] if rng is not None else 0
        cr.texts.append(_note_bytes(head, as_json))
        op.head = len(cr.texts) - 1
        cr.texts.append(_note_bytes(suffix, as_json))
        op.suffix = len(cr.texts) - 1
        op.enum = -1
        if enum is not None:
            cr.enums.append({k: _note_bytes(v, as_json) for k, v in enum.items()})
            op.enum = len(cr.enums) - 1
    cr.nops = len(compiled.answer)
    return cr


cdef int put_hex_number(Buf* o, uint64_t v, int digits) except -1:
    """``f"0x{v:0{digits}X}"``."""
    cdef char tmp[20]
    cdef int i = 20
    put(o, b"0x", 2)
    while v or 20 - i < digits:
        i -= 1
        tmp[i] = HEXD[v & 15]
        v >>= 4
    return put(o, tmp + i, 20 - i)


cdef int put_op(Buf* o, _CRead cr, Op* op, const uint8_t* words) except -1:
    """One note of a compiled answer (:func:`mbmon.semantics.values.format_value`)."""
    cdef const uint8_t* w = words + 2 * op.a
    cdef int64_t raw, mag
    cdef uint32_t u, low, high
    cdef float f
    cdef int i, n, shown
    cdef char tmp[24]
    put_bytes(o, cr.texts[op.head])
    if op.kind == 1:  # a run of plain words: at most 12, then "… (+N)"
        n = op.b - op.a
        shown = n if n < op.decimals else op.decimals
        for i in range(shown):
            if i:
                put_c(o, 32)
            raw = be16(w + 2 * i)
            if op.type == 1 and raw & 0x8000:
                raw -= 0x10000
            put_i(o, raw)
        if n > op.decimals:
            put_bytes(o, b" \xe2\x80\xa6 (+")
            put_i(o, n - op.decimals)
            put_c(o, 41)
        return 0
    if op.type <= 1:
        raw = be16(w)
        if op.type == 1 and raw & 0x8000:
            raw -= 0x10000
    else:
        if op.high_low:
            high = be16(w)
            low = be16(w + 2)
        else:
            low = be16(w)
            high = be16(w + 2)
        u = (high << 16) | low
        if op.type == 4:
            memcpy(&f, &u, 4)
            put_double(o, <double>f * op.scale, b'g', 6, 0)
            return put_bytes(o, cr.texts[op.suffix])
        raw = u
        if op.type == 3 and u & 0x80000000:
            raw = <int64_t>u - 0x100000000
    if op.fmt == 4 or op.fmt == 5:  # an enum
        name = (<dict>cr.enums[op.enum]).get(raw)
        if name is None:
            put_i(o, raw)
            put(o, b" (unknown)", 10)
        elif op.fmt == 4:
            put_bytes(o, name)
            put(o, b" (", 2)
            put_i(o, raw)
            put_c(o, 41)
        else:
            put_i(o, raw)
            put(o, b" (", 2)
            put_bytes(o, name)
            put_c(o, 41)
    elif op.fmt == 1:
        put_hex_number(o, <uint64_t>(raw & 0xFFFFFFFF), 4 * (op.b - op.a))
    elif op.fmt == 0:
        put_i(o, raw)
        put_bytes(o, cr.texts[op.suffix])
    elif op.fmt == 2:  # raw with a decimal point ``decimals`` digits from its end
        mag = -raw if raw < 0 else raw
        if raw < 0:
            put_c(o, 45)
        put_i(o, mag // op.divisor)
        put_c(o, 46)
        mag = mag % op.divisor
        for i in range(op.decimals - 1, -1, -1):
            tmp[i] = <char>(48 + mag % 10)
            mag //= 10
        put(o, tmp, op.decimals)
        put_bytes(o, cr.texts[op.suffix])
    else:  # F_SCALED: format(raw * scale, ".Nf")
        put_double(o, <double>raw * op.scale, b'f', op.decimals, 0)
        put_bytes(o, cr.texts[op.suffix])
    if op.has_range and not (op.lo <= raw <= op.hi):
        put(o, b" (out of range ", 15)
        put_i(o, op.lo)
        put(o, b"..", 2)
        put_i(o, op.hi)
        put_c(o, 41)
    return 0



_HELD_SIGNALS = {int(_signal_mod.SIGINT), int(_signal_mod.SIGTERM)}
# the C module under ``signal``: its pthread_sigmask takes and gives plain numbers, where
# the ``signal`` module's makes enums of them (4.3 us against 1.5 a block handed over)
_sigmask = getattr(_sys.modules.get("_signal", _signal_mod), "pthread_sigmask", None)


def _hold_signals():
    """SIGINT/SIGTERM blocked for this thread (kept pending by the kernel); the set to
    give back to :func:`_release_signals`, or None where that is not possible or not
    needed: Python's handlers run only in the main thread, so a block handed over in
    another (the proxy's pipe reader, after every read) cannot be cut by one."""
    if _threading.current_thread() is not _threading.main_thread():
        return None
    try:
        return _sigmask(_signal_mod.SIG_BLOCK, _HELD_SIGNALS)
    except (TypeError, OSError, ValueError):  # TypeError: no pthread_sigmask here
        return None


def _release_signals(before):
    if before is not None:
        _sigmask(_signal_mod.SIG_SETMASK, before)


cdef extern from *:
    """
    #if defined(__GLIBC__)
    #include <malloc.h>
    static int mb_keep_heap(void) {
        /* a log's ~1 MiB blocks, chunks and compressed chunks from the heap, kept */
        return mallopt(M_MMAP_THRESHOLD, 8 << 20) && mallopt(M_TRIM_THRESHOLD, 32 << 20)
            && mallopt(M_TOP_PAD, 8 << 20);
    }
    #else
    static int mb_keep_heap(void) { return 0; }
    #endif
    """
    int mb_keep_heap()


cdef bint _heap_kept = False
cdef size_t _block_at = 0  # where the last log block handed over was written (tests)


def _last_block_at():
    """Test-only: the address of the memory the core wrote its last handed-over log block
    in (the start of its bytes object's data when it went without a copy)."""
    return _block_at


cdef void keep_heap():
    """Make the C library keep freed memory for the next block (glibc: ``mallopt``).

    A log written at full speed allocates and frees a block (~1 MiB), its chunk and its
    compressed chunk per MiB of messages; by default glibc maps each of those fresh
    (``mmap`` above 128 KiB, or its heap trimmed back after each free), and the kernel
    then zeroes every page anew: about 150,000 page faults and 0.3 s of system time per
    million ADUs logged. Kept, they are reused: at most 32 MiB more of freed memory
    stays with the process. Once per process; nothing where the C library is not
    glibc."""
    global _heap_kept
    if not _heap_kept:
        _heap_kept = True
        mb_keep_heap()


cdef class _Pass:
    """One pass over a capture: every decision; with ``emit``, every line too."""

    cdef bint emit
    cdef bint as_json
    cdef double timeout
    cdef object ports           # frozenset of Modbus/TCP ports
    cdef bint detect            # the reference would look for Modbus on other TCP ports
    cdef object detector        # with detect: the reference's PortDetector, fed the same segments
    cdef uint8_t port_map[65536]  # the same, one byte per port
    cdef uint8_t ckey[64][12]   # a direct-mapped cache of the flow table (12-byte keys)
    cdef int cval[64]           # its values; -1: empty
    cdef object view
    cdef object tf
    cdef object write
    cdef public object release  # release(offset, length): the mapped file's pages read
    cdef Py_ssize_t released
    cdef public object progress  # progress(done, total) about once per MiB, or None
    cdef public Py_ssize_t progress_base  # bytes counted done before this pass
    cdef Py_ssize_t next_progress
    cdef Py_ssize_t size
    cdef Buf out
    # connections
    cdef Conn* conns
    cdef int nconns
    cdef int capconns
    cdef dict flows             # 12-byte key -> conn * 2 + (sender is client)
    cdef list open_order        # conn indexes in creation order (open ones are open_)
    cdef int nopen
    cdef object closed_fifo     # [conn, until] in closing order
    cdef double due
    # pairing
    cdef Pend* pool
    cdef int npool
    cdef int cappool
    cdef int free_head
    cdef int* table
    cdef int tbits
    cdef int tused
    cdef SPend* sp
    cdef int capsp
    cdef int ahead
    cdef int atail
    cdef int total
    cdef double next_tick
    cdef double last_ts
    cdef double end_ts
    # records and the summary
    cdef public int64_t index
    cdef public int64_t frames
    cdef public int64_t requests, responses, exceptions, timeouts, unsolicited, malformed
    cdef public int64_t max_stream
    cdef public bint robot_seen     # --robot: the summary's robot_seen (a new stream's role)
    # the filters and -c (``select``): which records the console shows, where the run ends
    cdef bint f_on                  # a filter decides which records are written
    cdef bint f_show                # the console shows lines (not -q)
    cdef bint f_grep                # --grep: the line is written, then tested
    cdef bint f_slow                # --where: every frame as the reference's Record
    cdef object flt                 # the RecordFilter (the reference's, for Python records)
    cdef object f_passes            # mbmon.sinks.select.passes
    cdef object f_needle            # --grep's text, lower case
    cdef bint f_units, f_fcs, f_addr, f_since, f_until
    cdef uint8_t f_umap[256]
    cdef uint8_t f_fmap[256]
    cdef int f_alo, f_ahi
    cdef double f_since_v, f_until_v
    cdef int64_t left               # -c: frames still to count; -1: no -c
    # where the filter's start is (first pass): the first record's time, the first
    # frame's, and the first frame's of the first batch (NaN: it had none)
    cdef int64_t batch, b1
    cdef public double rec0_ts, frame0_ts, b1_frame_ts
    cdef public bint any_frame
    # several inputs (``read A B``): the run's stream id of each of this pass's streams
    # (None: the same), and (first pass) how many streams this input had made when it
    # gave its first item (the reference's source reads it as it opens)
    cdef list sid_ext
    cdef public int open_streams
    cdef bint robot_on              # --robot given: robot_seen is looked for
    cdef bint robot_unsettled       # --robot, the view has seen fewer than two peers
    cdef public double first, last
    cdef public bint any_record
    cdef public dict events
    # emitting
    cdef list streams           # Stream objects, by id (made when a line needs one)
    cdef list labels            # per stream: (label C2S, label S2C) in UTF-8
    cdef list heads             # per stream: JSON '"src":"..","dst":".."' both ways
    cdef double second
    cdef bytes prefix
    cdef list fnames            # function names in UTF-8, None where not plain
    cdef list enames
    cdef list _sid_conn         # stream id -> connection index
    cdef double pl_last         # the pipeline's _last_ts (chunks set it, events raise it)
    # the MCAP log (-w x.mcap): message records made here, see "MCAP messages" below
    cdef object mcap            # the McapSink the blocks go to; None: no log
    cdef object mlayout         # its LogLayout
    cdef object totals          # the log's counters as of the last slow item (a Totals)
    cdef Buf mc                 # message records not handed over yet
    cdef Py_ssize_t mc_done     # mc's length at the end of the last whole item
    cdef uint64_t mc_first, mc_last
    cdef bint mc_any
    cdef bint swapped           # out and lnb exchanged (see swap_bufs)
    cdef int ch_raw, ch_frames, ch_monitor
    cdef int64_t d_req, d_resp, d_exc, d_chunks, d_bytes  # counted here since the last sync
    cdef int64_t d_left         # chunks whose /modbus/raw message was left out (format 4)
    # the /modbus/raw message mcap_chunk wrote last, while nothing came after it in mc
    # (format 4: the frame after it may take it back, frame_pb and mcap_items)
    cdef Py_ssize_t mr_at       # its head's offset in mc; -1: none
    cdef Py_ssize_t mr_end      # mc's length right after it
    cdef Py_ssize_t mr_n        # its chunk's length (the data that ends it)
    cdef int mr_sid, mr_d
    cdef double mr_ts
    cdef double rec_ts          # the last fast record's time (the counters' last_ts)
    cdef bint rec_any
    cdef double next_stats      # capture time of the next stats event (the totals')
    cdef list mprefix           # stream * 2 + direction -> its /modbus/raw prefix
    cdef list mtails            # stream -> its /modbus/monitor tail
    cdef Buf lnb                # a log's frame line (or JSON line) being made (swap_bufs)
    cdef uint64_t mon_sec       # the monitor timestamp's last ``sec`` + 1 (0: none yet)
    cdef char mon_sec_text[48]  # '{"timestamp":{"sec":' that sec ',"nsec":'
    cdef int mon_sec_n
    cdef list fheads            # stream * 2 + direction -> its modbus.Frame stream fields
    # --profile (the emitting pass only; annot None: no profile)
    cdef object annot           # the run's Annotator (mbmon.semantics.annotate)
    cdef dict pb                # (stream id << 8) | unit -> its _Bound, or None: no profile
    cdef dict pb_shared         # (server, unit) -> _Bound (a session is one per server and unit)
    cdef object cmd_summary     # a Summary fed the COMMAND records (the summary's commands)
    cdef Py_ssize_t* marks      # where each note of the line being written starts and ends
    cdef int capmarks
    # noise: directions the reference decoder frames (see "noise (the reference)")
    cdef bint stopped           # frames_of stopped at bytes that are no clean header
    cdef dict mdecs             # conn * 2 + direction -> its MbapDecoder
    cdef list dec_order         # conn * 2 + direction, in the order bytes first came
    cdef public int64_t noise_records, noise_bytes
    # TCP holes: connections the reference TcpConnection reassembles (see ref_segment)
    cdef dict pyconns           # conn -> its TcpConnection
    cdef object tcp_stats       # their TcpStats (the dissector's, not shown by read)
    cdef public bint live       # the streaming entry: it hands such packets over instead
    cdef int rec_iface          # pcapng: the interface of the record being read (pcap: 0)
    # the last packet that parsed up to TCP or UDP (``Dissector.good_ts``: where a
    # damaged capture ends; NaN: none yet)
    cdef public double good_ts
    # Modbus/UDP: pairs by both directions' keys (as flows), their stream ids
    cdef dict udp_pairs

    def __cinit__(self):
        self.marks = NULL
        self.capmarks = 0
        self.conns = NULL
        self.pool = NULL
        self.table = NULL
        self.sp = NULL
        self.out.p = NULL
        self.out.n = 0
        self.out.cap = 0
        self.out.box = NULL
        self.mc.p = NULL
        self.mc.n = 0
        self.mc.cap = 0
        self.mc.box = NULL
        self.lnb.p = NULL
        self.lnb.n = 0
        self.lnb.cap = 0
        self.lnb.box = NULL

    def __dealloc__(self):
        cdef int i, d
        if self.conns != NULL:
            for i in range(self.nconns):
                for d in range(2):
                    if self.conns[i].h[d].buf != NULL:
                        free(self.conns[i].h[d].buf)
            free(self.conns)
        free(self.pool)
        free(self.table)
        free(self.sp)
        free(self.out.p)
        buf_free(&self.mc)
        free(self.lnb.p)
        free(self.marks)

    def __init__(self, bint emit, bint as_json, double timeout, ports, view, write,
                 bint detect=False, annotator=None):
        self.emit = emit
        self.annot = annotator if emit else None
        self.pb = {}
        self.pb_shared = {}
        self.cmd_summary = None
        if self.annot is not None:
            from mbmon.sinks.summary import Summary

            self.cmd_summary = Summary(None)
        self.detect = detect
        self.detector = None
        if detect:
            from mbmon.analysis.detect import PortDetector

            self.detector = PortDetector()
        self.as_json = as_json
        self.timeout = timeout
        self.ports = ports
        memset(self.port_map, 0, 65536)
        for port in ports:
            if 0 <= port <= 0xFFFF:
                self.port_map[<int>port] = 1
        self.clear_cache()
        self.view = view
        self.tf = view.time_format if view is not None else None
        self.write = write
        self.release = None
        self.released = 0
        self.progress = None
        self.progress_base = 0
        self.next_progress = 0
        self.flows = {}
        self.mdecs = {}
        self.dec_order = []
        self.pyconns = {}
        self.udp_pairs = {}
        self.tcp_stats = TcpStats()
        self.live = False
        self.good_ts = float("nan")
        self.open_order = []
        self.nopen = 0
        self.closed_fifo = []
        self.due = float("inf")
        self.tbits = 10
        self.table = <int*>malloc(sizeof(int) << self.tbits)
        if self.table == NULL:
            raise MemoryError()
        for i in range(1 << self.tbits):
            self.table[i] = -1
        self.free_head = -1
        self.ahead = -1
        self.atail = -1
        self.next_tick = float("-inf")
        self.last_ts = 0.0
        self.end_ts = 0.0
        self.pl_last = 0.0
        self._sid_conn = []
        self.index = 0
        self.max_stream = -1
        self.robot_seen = False
        self.f_on = False
        self.f_slow = False
        self.f_show = True
        self.f_grep = False
        self.flt = None
        self.left = -1
        self.batch = 0
        self.b1 = -1
        self.rec0_ts = self.frame0_ts = self.b1_frame_ts = float("nan")
        self.any_frame = False
        self.sid_ext = None
        self.open_streams = -1
        self.robot_on = view is not None and view.robot is not None
        self.robot_unsettled = self.robot_on
        self.any_record = False
        self.events = {}
        self.streams = []
        self.labels = []
        self.heads = []
        self.second = float("nan")
        self.prefix = None
        self.fnames = []
        for fc in range(128):
            self.fnames.append(_plain(function_name(fc)))
        self.enames = []
        for code in range(256):
            self.enames.append(_plain(exception_name(code)))

    # ------------------------------------------------------------------ output

    cdef int flush_out(self) except -1:
        if self.out.n:
            if self.write is not None:  # None: a -q run writing only its log
                self.write(PyBytes_FromStringAndSize(self.out.p, self.out.n))
            self.out.n = 0
        return 0

    cdef int put_time(self, double ts) except -1:
        """``view.time_format.bytes(ts)``: its per-second prefix, then microseconds."""
        cdef double whole, x
        cdef int64_t us
        cdef char tmp[6]
        cdef int i
        if not isfinite(ts):
            return put_bytes(&self.out, self.tf.bytes(ts))
        whole = floor(ts)
        if whole != self.second:
            self.tf.bytes(ts)  # fills the format's own per-second cache (and its day)
            self.second = whole
            self.prefix = self.tf._second[2]
        if self.prefix is None:
            return put_bytes(&self.out, self.tf.bytes(ts))
        put_bytes(&self.out, self.prefix)
        x = (ts - whole) * 1e6 + 0.5
        us = 999999 if x > 999999.0 else <int64_t>x
        for i in range(5, -1, -1):
            tmp[i] = <char>(48 + us % 10)
            us //= 10
        return put(&self.out, tmp, 6)

    # ------------------------------------------------------------------ records

    cdef int count_record(self, double ts, int sid, bint frame) except -1:
        if not self.any_record:
            self.b1 = self.batch
            self.rec0_ts = ts
        if frame and not self.any_frame:
            self.any_frame = True
            self.frame0_ts = ts
            if self.batch == self.b1:
                self.b1_frame_ts = ts
        self.any_record = True
        if self.index == 0 or ts < self.first:
            self.first = ts
        if self.index == 0 or ts > self.last:
            self.last = ts
        if self.sid_ext is not None:
            sid = self.sid_ext[sid]
        if sid > self.max_stream:
            self.max_stream = sid
            if self.robot_on and not self.robot_seen:  # as Summary.on_records looks
                self.robot_seen = self.view.robot_role(self.stream_by_id(sid)) is not None
        self.index += 1
        return 0

    cdef object stream_obj(self, int sid):
        while len(self.streams) <= sid:
            self.streams.append(None)
            self.labels.append(None)
            self.heads.append(None)
        s = self.streams[sid]
        if s is None:
            s = self.streams[sid] = self.make_stream(sid)
        return s

    cdef object make_stream(self, int sid):
        """The Stream of ``sid`` (its endpoints as the flow table writes them)."""
        cdef Conn* c = &self.conns[self.conn_of_sid(sid)]
        if c.alen == 4:
            client = "%d.%d.%d.%d:%d" % (c.caddr[0], c.caddr[1], c.caddr[2], c.caddr[3], c.cport)
            server = "%d.%d.%d.%d:%d" % (c.saddr[0], c.saddr[1], c.saddr[2], c.saddr[3], c.sport)
        else:  # the flow table's own text of an IPv6 endpoint
            client = address_text(bytes(c.caddr[:16]), c.cport)
            server = address_text(bytes(c.saddr[:16]), c.sport)
        return Stream(sid if self.sid_ext is None else self.sid_ext[sid],
                      Transport.UDP if c.udp else Transport.TCP, client, server)

    cdef object stream_by_id(self, int64_t ext):
        """The Stream whose (run's) id is ``ext``."""
        if self.sid_ext is None:
            return self.stream_obj(<int>ext)
        return self.stream_obj(self.sid_ext.index(ext))

    def stream_count(self):
        """How many streams this pass made."""
        return len(self._sid_conn)

    def stream_ids(self, list ids):
        """The run's stream id of each stream this pass will make, in order (several
        inputs: the hub's allocator gives ids as the reference's sources make streams)."""
        self.sid_ext = ids

    cdef inline bint labels_missing(self, int sid):
        """Whether ``labels[sid]`` is still to be made (the common case: it is there)."""
        return sid >= len(self.labels) or self.labels[sid] is None

    cdef int stream_labels(self, int sid) except -1:
        """Make sure ``labels[sid]`` and ``heads[sid]`` are there (the view's labels in
        UTF-8, the JSON heads). With ``--robot`` the view's labels name the robot's peer
        once it has seen two (``View._label`` clears its cache then): every label made
        before is made again."""
        stream = self.stream_obj(sid)
        if self.robot_unsettled and len(self.view._peers) >= 2:
            self.robot_unsettled = False
            for i in range(len(self.labels)):
                self.labels[i] = None
        if self.labels[sid] is None:
            self.labels[sid] = (
                self.view.label(stream, Direction.C2S).encode("utf-8"),
                self.view.label(stream, Direction.S2C).encode("utf-8"),
            )
        if self.heads[sid] is None:
            self.heads[sid] = (
                _inner(_orjson.dumps({"stream": stream.id, "src": stream.client,
                                      "dst": stream.server})),
                _inner(_orjson.dumps({"stream": stream.id, "src": stream.server,
                                      "dst": stream.client})),
            )
        return 0

    cdef int conn_of_sid(self, int sid) except -1:
        return self._sid_conn[sid]

    cdef int event(self, double ts, int sid, object kind, object info) except -1:
        """An event record (connect, disconnect, timeout), formatted by mbmon.format."""
        cdef int64_t index = self.index
        name = kind.value
        self.events[name] = self.events.get(name, 0) + 1
        if kind is EventKind.TIMEOUT:
            self.timeouts += 1
        else:  # a source's event, fed to the pipeline: a batch of records of its own
            self.batch += 1
            if self.open_streams < 0:
                self.open_streams = len(self._sid_conn)
            if ts > self.pl_last:
                self.pl_last = ts
        self.count_record(ts, sid, False)
        if not self.emit:
            return 0
        stream = self.stream_obj(sid)
        ev = Event(ts, stream, kind) if info is None else Event(ts, stream, kind, info)
        rec = Record(index, ts, RecordKind.EVENT, stream, event=ev)
        return self.put_record(rec)

    cdef int put_record(self, object rec) except -1:
        cdef bint ok = True
        if self.f_on or self.left >= 0:  # the filters and -c (``select``)
            if self.mcap is not None:  # the log is not behind the filters
                self.mcap_items([self.mlayout.waiting_item(rec)])
            if self.f_on:
                ok = self.f_passes(self.flt, rec, self.view)
            if ok and self.f_show:
                self.put_console_line(rec)
            if ok and self.left > 0 and rec.frame is not None:
                self.left -= 1
                if self.left == 0:
                    self.flush_out()
                    raise Enough()
            return 0
        return self.put_record_line(rec)

    cdef int put_record_line(self, object rec) except -1:
        """A record the reference way: its line or JSON line (and log messages)."""
        if self.mcap is not None:
            self.mcap_items([self.mlayout.waiting_item(rec)])
            if self.write is None:
                return 0
        return self.put_console_line(rec)

    cdef int put_console_line(self, object rec) except -1:
        """A record's line or JSON line on the console, the reference way."""
        if self.as_json:
            put_bytes(&self.out, record_json_bytes(rec, self.view))
        else:
            put_bytes(&self.out, record_line(rec, self.view).encode("utf-8", "backslashreplace"))
        put_c(&self.out, 10)
        if self.out.n >= FLUSH_AT:
            self.flush_out()
        return 0

    cdef int frame_record(self, int sid, int d, double ts, const uint8_t* adu, int alen,
                          Pend* req) except -1:
        """The record of one frame: a request, or a response with its request (``req``)
        or without (NULL)."""
        cdef int64_t index = self.index
        cdef uint8_t code = adu[7]
        cdef Native nat, rnat
        cdef bint native
        cdef double latency = 0.0
        if d == 0:
            self.requests += 1
        elif code & 0x80:
            self.exceptions += 1
        else:
            self.responses += 1
        if d == 1 and req == NULL:
            self.unsolicited += 1
        self.count_record(ts, sid, True)
        if not self.emit:
            return 0
        if req != NULL:
            latency = ts - req.ts
        if self.annot is not None:
            bound = self.bound_of(sid, adu[6])
            if bound is not None:
                return self.prof_frame(<_Bound>bound, index, sid, d, ts, adu, alen, req, latency)
        # the PDUs this module formats itself; the rest goes to mbmon.format
        if d == 0:
            native = native_pdu(adu + 7, alen - 7, False, NULL, &nat)
        elif req != NULL:
            native = (native_pdu(req.raw + 7, req.alen - 7, False, NULL, &rnat)
                      and native_pdu(adu + 7, alen - 7, True, &rnat, &nat))
        else:
            native = native_pdu(adu + 7, alen - 7, True, NULL, &nat)
        if native and self.fnames[nat.fc] is None:
            native = False
        if native and nat.exc >= 0 and self.enames[nat.exc] is None:
            native = False
        if native and self.mcap is not None and not self.mcap_fast(ts):
            native = False  # a stats event is due, or a time MCAP clamps: the layout's way
        if self.f_slow:
            native = False  # --where: its test reads the reference's Record
        if not native:
            return self.python_frame(index, sid, d, ts, adu, alen, req, latency)
        if req != NULL and nat.kind != 0 and not nat.has_addr and rnat.has_addr:
            # a response's address and count are its read request's (the JSON's, the note's)
            nat.has_addr = 1
            nat.address = rnat.address
            nat.count = rnat.count
        if (self.f_on and not self.f_grep and self.mcap is None
                and not self.fast_pass(ts, adu[6], &nat)):
            return 0  # not shown, not counted by -c (nothing of it formatted: no label)
        if self.robot_unsettled or self.labels_missing(sid):
            self.stream_labels(sid)
        cdef bint mc = self.mcap is not None
        cdef bint js = self.as_json  # a log's messages need the line alone (frame_pb)
        if mc:  # the line goes into lnb, read from there into the log's messages and the
            self.swap_bufs()  # console (put_time, put_note write to out)
            self.out.n = 0
        cdef Buf* o = &self.out
        cdef Py_ssize_t note_at, note_end, line_at, line_end
        cdef Py_ssize_t rec_at = o.n
        cdef bytes label = self.labels[sid][d]
        cdef int tid = (adu[0] << 8) | adu[1]
        cdef int unit = adu[6]
        if js:
            put(o, b'{"index":', 9)
            put_i(o, index)
            put(o, b',"time":', 8)
            put_json_time(o, ts)
            put_c(o, 44)
            put_bytes(o, self.heads[sid][d])
            put(o, b',"transport":"tcp","tid":', 25)
            put_u(o, tid)
            put(o, b',"unit":', 8)
            put_u(o, unit)
            put(o, b',"fc":', 6)
            put_u(o, nat.fc)
            if nat.kind == 0:
                put(o, b',"kind":"request","exception_code":', 35)
            elif nat.kind == 1:
                put(o, b',"kind":"response","exception_code":', 36)
            else:
                put(o, b',"kind":"exception","exception_code":', 37)
            if nat.exc >= 0:
                put_u(o, nat.exc)
            else:
                put(o, b"null", 4)
            put(o, b',"address":', 11)
            if nat.has_addr:
                put_u(o, nat.address)
            else:
                put(o, b"null", 4)
            put(o, b',"count":', 9)
            if nat.has_addr and nat.count >= 0:
                put_u(o, nat.count)
            else:
                put(o, b"null", 4)
            put(o, b',"values":', 10)
            put_values_json(o, &nat)
            put(o, b',"pdu":"', 8)
            put_hex(o, adu + 7, alen - 7)
            put(o, b'","line":"', 10)
        line_at = o.n
        self.put_line_head(o, ts, label, unit, tid, adu, alen)
        note_at = o.n
        self.put_note(&nat)
        note_end = o.n
        if req != NULL:
            put(o, b" (", 2)
            put_double(o, latency * 1000, b'f', 1, 0)
            put(o, b" ms)", 4)
        elif d == 1:
            put(o, b" (no matching request)", 22)
        line_end = o.n
        if js:
            put(o, b'","notes":["', 12)
            buf_need(o, note_end - note_at)
            memcpy(o.p + o.n, o.p + note_at, note_end - note_at)
            o.n += note_end - note_at
            put(o, b'"],"crc_ok":null,"latency_ms":', 30)
            self.put_json_answer_tail(o, req, latency)
        if mc:
            self.frame_pb(index, sid, d, ts, tid, unit, &nat, adu, alen, req, latency,
                          note_at, note_end)
            return self.mcap_frame(line_at, line_end, index, sid, ts, nat.kind,
                                   d == 1 and req == NULL, &nat, adu[6])
        put_c(o, 10)
        if self.f_on or self.left >= 0:
            return self.selected(rec_at, line_at, line_end, ts, adu[6], &nat, False)
        if o.n >= FLUSH_AT:
            self.flush_out()
        return 0

    # ------------------------------------------------------------------ filters and -c
    #
    # The reference puts the console behind the filters (``Selection``) and every
    # output behind ``-c`` (``FrameBudget``): a native frame is tested on its fields
    # before anything of it is formatted (``fast_pass``), or with ``--grep`` formatted
    # first and its line tested (the reference formats every record's line then too);
    # every other record goes through the reference's own ``passes``.

    def select(self, flt, count, bint show):
        """Make this (writing) pass show only what ``flt`` (an active ``RecordFilter``,
        its start resolved, or ``None``) lets through when ``show``, and end after
        ``count`` frames it lets through (``None``: no ``-c``)."""
        from mbmon.sinks.select import passes

        self.f_passes = passes
        self.f_show = show
        self.left = -1 if count is None else count
        self.f_on = flt is not None and (show or count is not None)
        if not self.f_on:
            return
        self.flt = flt
        self.f_slow = flt.where is not None
        self.f_grep = flt.grep is not None
        self.f_needle = flt.grep.lower() if self.f_grep else None
        self.f_units = flt.units is not None
        self.f_fcs = flt.fcs is not None
        self.f_addr = flt.address is not None
        self.f_since = flt.since is not None
        self.f_until = flt.until is not None
        memset(self.f_umap, 0, 256)
        memset(self.f_fmap, 0, 256)
        for unit in flt.units or ():
            self.f_umap[<int>unit & 0xFF] = 1
        for fc in flt.fcs or ():
            self.f_fmap[<int>fc & 0xFF] = 1
        if self.f_addr:
            self.f_alo, self.f_ahi = flt.address
        self.f_since_v = flt.since if self.f_since else 0.0
        self.f_until_v = flt.until if self.f_until else 0.0

    def flush(self):
        """Write what the output buffer holds (a run ended by ``-c``)."""
        self.flush_out()

    def next_input(self):
        """Another capture follows the one this pass read (``read A B``): as the
        reference reads it, alone — a fresh dissector (no connection of the last one
        goes on; its end already closed them and timed its requests out) and the
        pipeline's clock started again — while the record numbers, the stream ids, the
        counts, the view and the filters go on."""
        self.flows = {}
        self.open_order = []
        self.nopen = 0
        self.closed_fifo = []
        self.due = float("inf")
        self.clear_cache()
        self.next_tick = float("-inf")
        self.last_ts = 0.0
        self.end_ts = 0.0
        self.pl_last = 0.0
        self.released = 0
        self.next_progress = 0
        self.batch += 1

    cdef bint fast_pass(self, double ts, int unit, Native* n):
        """``RecordFilter.matches_record`` of a native frame, but ``--grep``."""
        cdef int64_t span
        if self.f_since and not ts >= self.f_since_v:
            return False
        if self.f_until and not ts <= self.f_until_v:
            return False
        if self.f_units and not self.f_umap[unit]:
            return False
        if self.f_fcs and not self.f_fmap[n.fc & 0xFF]:
            return False
        if self.f_addr:
            if not n.has_addr:
                return False
            span = n.count if n.count > 0 else 1
            if not (n.address <= self.f_ahi and n.address + span - 1 >= self.f_alo):
                return False
        return True

    cdef int selected(self, Py_ssize_t rec_at, Py_ssize_t line_at, Py_ssize_t line_end,
                      double ts, int unit, Native* n, bint escaped) except -1:
        """A native frame's record was written at ``rec_at`` (its line at ``line_at``,
        JSON-escaped when ``escaped``): with ``--grep`` its line decides (taken back when
        it fails); -c counts it."""
        cdef Buf* o = &self.out
        if self.f_grep:
            if escaped:
                line = _orjson.loads(b'"' + PyBytes_FromStringAndSize(o.p + line_at,
                                                                     line_end - line_at) + b'"')
            else:
                line = PyUnicode_DecodeUTF8(o.p + line_at, line_end - line_at, NULL)
            if not self.fast_pass(ts, unit, n) or self.f_needle not in line.lower():
                o.n = rec_at
                return 0
        if not self.f_show:
            o.n = rec_at
        if self.left > 0:
            self.left -= 1
            if self.left == 0:
                self.flush_out()
                raise Enough()
        if o.n >= FLUSH_AT:
            self.flush_out()
        return 0

    cdef int put_note(self, Native* n) except -1:
        """The generic note (``mbmon.format.generic_note``) of a native PDU."""
        cdef Buf* o = &self.out
        cdef int i, shown, bit
        if n.kind == 2:
            put(o, b"Exception ", 10)
            put_c(o, HEXD[n.exc >> 4])
            put_c(o, HEXD[n.exc & 15])
            put_c(o, 32)
            put_bytes(o, self.enames[n.exc])
            put(o, b" (", 2)
            put_bytes(o, self.fnames[n.fc])
            put_c(o, 41)
            return 0
        put_bytes(o, self.fnames[n.fc])
        if n.has_addr:
            put_c(o, 32)
            put_u(o, n.address)
            if n.count > 1:
                put(o, b"..", 2)
                put_u(o, n.address + n.count - 1)
        if n.nvalues > 0:
            put(o, b" = ", 3)
            if n.onoff:
                if n.vdata[0]:
                    put(o, b"ON", 2)
                else:
                    put(o, b"OFF", 3)
            elif n.bits:
                shown = n.nvalues if n.nvalues < 64 else 64
                buf_need(o, shown)
                for i in range(shown):
                    bit = (n.vdata[i >> 3] >> (i & 7)) & 1
                    o.p[o.n] = 49 if bit else 48
                    o.n += 1
                if n.nvalues > 64:
                    put(o, b"\xe2\x80\xa6", 3)
            else:
                shown = n.nvalues if n.nvalues < 16 else 16
                buf_need(o, 7 * shown)  # ", " and up to five digits each
                for i in range(shown):
                    if i:
                        o.p[o.n] = 44
                        o.p[o.n + 1] = 32
                        o.n += 2
                    o.n += u16_text(o.p + o.n, be16(n.vdata + 2 * i))
                if n.nvalues > 16:
                    put(o, b", \xe2\x80\xa6 (", 7)
                    put_u(o, n.nvalues)
                    put(o, b" values)", 8)
        return 0

    cdef int put_json_answer_tail(self, Buf* o, Pend* req, double latency) except -1:
        """A JSON frame line's end after ``"latency_ms":``: the latency (rounded as the
        reference rounds it; null without a request), ``malformed`` and the request's index."""
        if req != NULL and fabs(latency) < 1e9:
            put_json_round3(o, latency * 1000)
        elif req != NULL:
            put_bytes(o, _orjson.dumps(round(latency * 1000, 3)))
        else:
            put(o, b"null", 4)
        put(o, b',"malformed":null,"request_index":', 34)
        if req != NULL:
            put_i(o, req.index)
        else:
            put(o, b"null", 4)
        put_c(o, 125)
        return 0

    cdef int put_line_head(self, Buf* o, double ts, bytes label, int unit, int tid,
                           const uint8_t* adu, int alen) except -1:
        """A frame line up to its notes: time, the stream's label, unit, transaction id,
        the PDU in hex and the notes' separator."""
        self.put_time(ts)
        put(o, b"  ", 2)
        put_bytes(o, label)
        put(o, b"  [u", 4)
        put_u(o, unit)
        put(o, b" t", 2)
        put_u(o, tid)
        put(o, b"]  ", 3)
        put_hex(o, adu + 7, alen - 7)
        put(o, b"  | ", 4)
        return 0

    cdef int python_frame(self, int64_t index, int sid, int d, double ts, const uint8_t* adu,
                          int alen, Pend* req, double latency) except -1:
        """A frame record the reference way: its Frame and Record, formatted by mbmon.format."""
        stream, frame, request, req_index, lat = self.ref_frames(sid, d, ts, adu, alen, req,
                                                                latency)
        kind = _RECORD_KIND[frame.pdu.kind]
        rec = Record(index, ts, kind, stream, frame, request if d else None, req_index, lat)
        return self.put_record(rec)

    cdef tuple ref_frames(self, int sid, int d, double ts, const uint8_t* adu, int alen,
                          Pend* req, double latency):
        """The reference's objects of a frame: its stream, its Frame (the PDU decoded as
        the pairer decodes it, given the request), the request's Frame, index and the
        latency (``None`` each without a request); counts a malformed PDU."""
        stream = self.stream_obj(sid)
        raw = PyBytes_FromStringAndSize(<const char*>adu, alen)
        tid = (adu[0] << 8) | adu[1]
        pdu = decode_pdu(raw[7:], d == 1)
        if alen > 6 + MBAP_CLEAN:  # the decoder's mark of an MBAP length 255
            pdu = with_malformed(pdu, "MBAP length %d exceeds %d" % (alen - 6, MBAP_CLEAN))
        request = None
        req_index = None
        lat = None
        if req != NULL:
            req_raw = PyBytes_FromStringAndSize(<const char*>req.raw, req.alen)
            req_pdu = decode_pdu(req_raw[7:], False)
            if req.alen > 6 + MBAP_CLEAN:
                req_pdu = with_malformed(req_pdu, "MBAP length %d exceeds %d"
                                         % (req.alen - 6, MBAP_CLEAN))
            request = Frame(req.ts, stream, Direction.C2S, req.unit, req.tid, req_pdu, req_raw,
                            None)
            if _needs_request(pdu, req_pdu):
                pdu = decode_pdu(pdu.raw, True, request=req_pdu)
            req_index = req.index
            lat = latency
        frame = Frame(ts, stream, Direction.S2C if d else Direction.C2S, adu[6], tid, pdu, raw,
                      None)
        if pdu.malformed:
            self.malformed += 1
        return stream, frame, request, req_index, lat

    # ------------------------------------------------------------------ MCAP messages
    #
    # With a log (``-w x.mcap``), the writing pass makes its message records here, byte
    # for byte what ``LogLayout.convert`` makes of the same chunks and records: the
    # common frame record (its /modbus/frames message is the JSON line, its
    # /modbus/monitor message the line cut out of it) and every captured chunk (its
    # /modbus/raw message) without a Python object; every other record (events, frames
    # the reference formats, a frame at which a stats event is due, a time MCAP clamps)
    # goes through the layout itself with the log's counters brought up to date. The
    # records go to the sink in blocks of about 1 MiB with the counters as of their end.

    def log_to(self, sink):
        """Make this (writing) pass write ``sink``'s messages (an open ``McapSink``)."""
        from mbmon.io.mcap.layout import TOPIC_FRAMES, TOPIC_MONITOR, TOPIC_RAW

        self.mcap = sink
        self.mlayout = sink.layout
        keep_heap()
        if self.mc.box == NULL and self.mc.n == 0:
            buf_free(&self.mc)
            box_new(&self.mc, BLOCK_ROOM)
        channels = self.mlayout.channels
        self.ch_raw = channels[TOPIC_RAW]
        self.ch_frames = channels[TOPIC_FRAMES]
        self.ch_monitor = channels[TOPIC_MONITOR]
        self.totals = self.mlayout.new_totals()
        self.next_stats = self.totals.next_stats
        self.mprefix = []
        self.mtails = []
        self.fheads = []
        self.mc_any = False
        self.mr_at = -1

    def finish_log(self, bint complete=True):
        """Hand the last message records over (after the run, or after it was cut short:
        then only whole items')."""
        if self.mcap is None:
            return
        if self.swapped:  # cut short while a line was being written
            self.swap_bufs()
        if not complete:
            self.mc.n = self.mc_done
        self.flush_mcap()

    cdef inline void swap_bufs(self) noexcept:
        """Exchange ``out`` and ``lnb`` (``frame_record`` writes a log's line as ``out``)."""
        cdef Buf t = self.out
        self.out = self.lnb
        self.lnb = t
        self.swapped = not self.swapped

    cdef inline bint mcap_fast(self, double ts) noexcept:
        """Whether a frame record at ``ts`` is made here: no stats event due, a time
        whose log time MCAP holds (the layout's inline ``log_time_ns``)."""
        return 0.0 < ts < MAX_TS and ts < self.next_stats

    cdef inline int mc_span(self, uint64_t lt) noexcept:
        if not self.mc_any:
            self.mc_first = lt
            self.mc_last = lt
            self.mc_any = True
        elif lt < self.mc_first:
            self.mc_first = lt
        elif lt > self.mc_last:
            self.mc_last = lt
        return 0

    cdef int sync_totals(self) except -1:
        """Add what was counted here since the last sync to the log's counters."""
        t = self.totals
        if self.d_req or self.d_resp or self.d_exc:
            kinds = t.kinds
            kinds[RecordKind.REQUEST] += self.d_req
            kinds[RecordKind.RESPONSE] += self.d_resp
            kinds[RecordKind.EXCEPTION] += self.d_exc
            self.d_req = self.d_resp = self.d_exc = 0
        if self.d_chunks:
            counts = t.counts
            counts["chunks"] += self.d_chunks
            counts["bytes"] += self.d_bytes
            self.d_chunks = self.d_bytes = 0
        if self.d_left:
            t.left_out += self.d_left
            self.d_left = 0
        if self.rec_any:
            t.last_ts = self.rec_ts
            self.rec_any = False
        return 0

    cdef int flush_mcap(self) except -1:
        """The message records so far to the sink, with the counters as of their end.

        A block is handed over whole or not at all: SIGINT/SIGTERM are held back by the
        kernel meanwhile, and one already noted is acted on first (its exception leaves
        the block here, for :meth:`finish_log`), so a signal can never land inside the
        sink's Python code before it took the block (a block lost, lines printed that
        the log does not hold)."""
        global _block_at
        if self.mc.n == 0:
            return 0
        blocked = _hold_signals()
        try:
            PyErr_CheckSignals()
            self.sync_totals()
            totals = self.totals.copy()
            self.mr_at = -1  # handed over: no frame takes its chunk's message back now
            _block_at = <size_t>self.mc.p
            if self.mc.box != NULL and self.mc.n >= HAND_WHOLE:
                # the bytes object the block was written in goes to the sink as it is
                # (handed over once: the core keeps nothing of it, whatever the sink
                # does), and the next block gets a fresh one once the sink is done
                data = box_take(&self.mc)
                self.mc_done = 0
                self.mc_any = False
                self.mcap.put_packed(data, self.mc_first, self.mc_last, totals)
                data = None  # written: the next block may reuse its memory
                box_new(&self.mc, BLOCK_ROOM)
            else:  # a short block (a live run's read, the last one): copied, room kept
                data = PyBytes_FromStringAndSize(self.mc.p, self.mc.n)
                self.mcap.put_packed(data, self.mc_first, self.mc_last, totals)
                self.mc.n = 0
                self.mc_done = 0
                self.mc_any = False
        finally:
            _release_signals(blocked)
        return 0

    cdef int mcap_items(self, list items) except -1:
        """Chunks and waiting records the layout makes into messages (and counts).

        Format 4: when the last thing in ``mc`` is a chunk's /modbus/raw message
        (``mcap_chunk``) and the first item a frame record, the chunk is taken back out
        of ``mc`` (and out of the counts) and goes to the layout in front of the items,
        whose own rule (``chunk_marker``) decides whether its message is left out."""
        cdef Py_ssize_t at = self.mr_at
        if at >= 0:
            self.mr_at = -1
            if (self.mc.n == self.mr_end and type(items[0]) is tuple
                    and items[0][0].kind in _FRAME_KINDS):
                data = PyBytes_FromStringAndSize(self.mc.p + self.mr_end - self.mr_n,
                                                 self.mr_n)
                items.insert(0, Chunk(self.mr_ts, self.stream_obj(self.mr_sid),
                                      Direction.S2C if self.mr_d else Direction.C2S, data))
                self.mc.n = at
                self.mc_done = at
                self.d_chunks -= 1
                self.d_bytes -= self.mr_n
        self.sync_totals()
        records, first, last, totals = self.mlayout.convert(items, self.totals)
        for r in records:
            put_bytes(&self.mc, r)
        if first >= 0:
            self.mc_span(first)
            self.mc_span(last)
        self.totals = totals
        self.next_stats = totals.next_stats
        self.mc_done = self.mc.n
        if self.mc.n >= FLUSH_AT:
            self.flush_mcap()
        return 0

    cdef bytes raw_prefix(self, int sid, int d):
        """A stream direction's /modbus/raw message up to its ``ts`` value (the layout's)."""
        cdef int k = sid * 2 + d
        while len(self.mprefix) <= k:
            self.mprefix.append(None)
        prefix = self.mprefix[k]
        if prefix is None:
            prefix = self.mlayout.raw_prefix(
                self.stream_obj(sid), Direction.S2C if d else Direction.C2S)
            self.mprefix[k] = prefix
        return prefix

    cdef bytes monitor_tail(self, int sid):
        """A stream's /modbus/monitor tail (name, file, "line" key: the layout's)."""
        while len(self.mtails) <= sid:
            self.mtails.append(None)
        tail = self.mtails[sid]
        if tail is None:
            tail = self.mlayout.monitor_tail(self.stream_obj(sid))
            self.mtails[sid] = tail
        return tail

    cdef int mcap_chunk(self, int sid, int d, double ts, const uint8_t* p,
                        Py_ssize_t n) except -1:
        """A captured chunk's /modbus/raw message (``LogLayout.convert``'s chunk branch).

        The block is never handed over right after it (it is before, when full): the
        frame record that comes next may take the message back (format 4: ``frame_pb``,
        ``mcap_items``), so it is remembered while it is the last thing in ``mc``."""
        cdef Buf* m = &self.mc
        cdef Py_ssize_t at
        cdef uint64_t lt
        self.mr_at = -1
        if m.n >= FLUSH_AT:
            self.flush_mcap()
        if not (0.0 < ts < MAX_TS):
            return self.mcap_items([Chunk(ts, self.stream_obj(sid),
                                          Direction.S2C if d else Direction.C2S,
                                          PyBytes_FromStringAndSize(<const char*>p, n))])
        cdef bytes prefix = self.raw_prefix(sid, d)
        cdef Py_ssize_t pn = len(prefix)
        lt = <uint64_t>rint(ts * 1e6) * 1000
        at = m.n
        buf_need(m, 31 + pn + 20 + n)  # the head, the prefix, ts and the data's length
        m.n += 31
        put_in_room(m, <const char*>prefix, pn)  # modbus.Raw (format 3): the prefix, ts, data
        c_in_room(m, 0x41)
        memcpy(m.p + m.n, &ts, 8)  # a protobuf double (put_f64)
        m.n += 8
        c_in_room(m, 0x4A)
        varint_in_room(m, <uint64_t>n)
        put_in_room(m, <const char*>p, n)
        put_head(m.p + at, m.n - at - 31, self.ch_raw, lt)
        self.d_chunks += 1
        self.d_bytes += n
        self.mc_span(lt)
        self.mc_done = m.n
        self.mr_at = at
        self.mr_end = m.n
        self.mr_n = n
        self.mr_sid = sid
        self.mr_d = d
        self.mr_ts = ts
        return 0

    cdef bytes frame_head(self, int sid, int d):
        """A stream direction's modbus.Frame fields stream, src, dst, transport (the
        layout's encoder, once per stream direction)."""
        cdef int k = sid * 2 + d
        while len(self.fheads) <= k:
            self.fheads.append(None)
        head = self.fheads[k]
        if head is None:
            head = _encode_frame(_orjson.loads(b"{" + self.heads[sid][d]
                                               + b',"transport":"tcp"}'))
            self.fheads[k] = head
        return head

    cdef int frame_pb(self, int64_t index, int sid, int d, double ts, int tid, int unit,
                      Native* nat, const uint8_t* adu, int alen, Pend* req, double latency,
                      Py_ssize_t note_at, Py_ssize_t note_end) except -1:
        """A native frame's /modbus/frames message record (log format 3), written where
        it ends up, at the end of ``mc``: the ``modbus.Frame`` that
        ``mbmon.io.mcap.proto.encode_frame`` makes of the format-2 object of its JSON
        line, field for field in the object's member order (its note is read from the
        line, written into ``out``, ``lnb`` while swapped: the native notes need no JSON
        escapes).

        Format 4 (``LogLayout``'s ``chunk_marker``): when the last thing in ``mc`` is the
        /modbus/raw message of a chunk of this stream direction at this time whose bytes
        are exactly this ADU (protocol id 0, its length field right), the frame is
        written over that message and ends with the marker of its direction."""
        cdef Buf* b = &self.mc
        cdef int i
        cdef double lat
        cdef Py_ssize_t at = b.n
        cdef bytes head = self.frame_head(sid, d)
        cdef Py_ssize_t hn = len(head), nn = note_end - note_at
        cdef bint left_out = False
        if (self.mr_at >= 0 and b.n == self.mr_end and self.mr_sid == sid and self.mr_d == d
                and self.mr_ts == ts and self.mr_n == alen and alen >= 7
                and adu[2] == 0 and adu[3] == 0 and (adu[4] << 8 | adu[5]) == alen - 6
                and memcmp(b.p + b.n - alen, adu, alen) == 0):
            left_out = True
            at = self.mr_at
            b.n = at
            self.mc_done = at  # the chunk is whole again with this frame's messages
            self.d_left += 1
        self.mr_at = -1
        # room for all of it at once (fixed fields and varints at most 200 bytes, the
        # marker 6)
        buf_need(b, 206 + hn + 3 * nat.nvalues + alen + nn)
        b.n += 31
        c_in_room(b, 0x08)
        varint_in_room(b, <uint64_t>index)
        c_in_room(b, 0x11)
        memcpy(b.p + b.n, &ts, 8)  # a protobuf double (put_f64)
        b.n += 8
        put_in_room(b, <const char*>head, hn)
        c_in_room(b, 0x38)
        varint_in_room(b, <uint64_t>tid)
        c_in_room(b, 0x40)
        varint_in_room(b, <uint64_t>unit)
        c_in_room(b, 0x48)
        varint_in_room(b, <uint64_t>nat.fc)
        if nat.kind == 0:
            put_in_room(b, b"\x52\x07request", 9)
        elif nat.kind == 1:
            put_in_room(b, b"\x52\x08response", 10)
        else:
            put_in_room(b, b"\x52\x09exception", 11)
        if nat.exc >= 0:
            c_in_room(b, 0x58)
            varint_in_room(b, <uint64_t>nat.exc)
        if nat.has_addr:
            c_in_room(b, 0x60)
            varint_in_room(b, <uint64_t>nat.address)
            if nat.count >= 0:
                c_in_room(b, 0x68)
                varint_in_room(b, <uint64_t>nat.count)
        if nat.nvalues > 0:
            c_in_room(b, 0x72)
            if nat.onoff or nat.bits:  # one byte a value
                varint_in_room(b, <uint64_t>nat.nvalues)
                for i in range(nat.nvalues):
                    if nat.onoff:
                        b.p[b.n] = 1 if nat.vdata[0] else 0
                    else:
                        b.p[b.n] = (nat.vdata[i >> 3] >> (i & 7)) & 1
                    b.n += 1
            else:
                put_packed_words(b, nat.vdata, nat.nvalues)
        c_in_room(b, 0x7A)
        varint_in_room(b, <uint64_t>(alen - 7))
        put_in_room(b, <const char*>adu + 7, alen - 7)
        put_in_room(b, b"\x82\x01", 2)
        varint_in_room(b, <uint64_t>nn)
        put_in_room(b, self.out.p + note_at, nn)  # out is lnb here
        if req != NULL:
            if fabs(latency) < 1e9:
                lat = py_round3(latency * 1000)
            else:
                lat = round(latency * 1000, 3)
            put_in_room(b, b"\x91\x01", 2)
            memcpy(b.p + b.n, &lat, 8)
            b.n += 8
            put_in_room(b, b"\xa0\x01", 2)
            varint_in_room(b, <uint64_t>req.index)
        if nat.nvalues == 0:  # [] is no packed field: the encoder's extra member
            put_in_room(b, b'\xf2\x01\x0d{"values":[]}', 16)
        if left_out:  # chunk = "c2s" / "s2c", field 21 (CHUNK_MARKS)
            put_in_room(b, b"\xaa\x01\x03s2c" if d else b"\xaa\x01\x03c2s", 6)
        put_head(b.p + at, b.n - at - 31, self.ch_frames, <uint64_t>rint(ts * 1e6) * 1000)
        return 0

    cdef int put_mon_time(self, Buf* m, uint64_t lt) except -1:
        """A /modbus/monitor message's timestamp up to its nanoseconds' digits; the text
        up to them made once a second."""
        cdef uint64_t sec = lt // 1000000000
        cdef Buf t
        if sec + 1 != self.mon_sec:
            t.p = self.mon_sec_text
            t.n = 0
            t.cap = 48  # 20 + at most 20 digits + 8: never grown
            t.box = NULL
            put(&t, b'{"timestamp":{"sec":', 20)
            put_u(&t, sec)
            put(&t, b',"nsec":', 8)
            self.mon_sec_n = <int>t.n
            self.mon_sec = sec + 1
        put(m, self.mon_sec_text, self.mon_sec_n)
        return put_u(m, lt % 1000000000)

    cdef int mcap_frame(self, Py_ssize_t line_at, Py_ssize_t line_end,
                        int64_t index, int sid, double ts, int kind,
                        bint unsolicited, Native* nat, int unit) except -1:
        """A frame record whose line (the JSON line with ``--json``) was just written into
        ``lnb`` and whose /modbus/frames message ``frame_pb`` wrote into ``mc``: its
        /modbus/monitor message after it, the console's line or JSON (when the filters
        let it through: the log keeps every record), its counts (the layout's fast path
        for frame records); ``-c``'s last frame ends the run once its messages are
        whole."""
        self.swap_bufs()  # back: the line was written into lnb as out
        cdef Buf* m = &self.mc
        cdef const char* ln = self.lnb.p
        cdef Py_ssize_t at
        cdef uint64_t lt = <uint64_t>rint(ts * 1e6) * 1000
        cdef bint warning = kind == 2 or unsolicited
        cdef bint ok = True
        if self.f_on:
            ok = self.fast_pass(ts, unit, nat)
            if ok and self.f_grep:
                line = PyUnicode_DecodeUTF8(ln + line_at, line_end - line_at, NULL)
                ok = self.f_needle in line.lower()
        if self.write is not None and ok:
            if self.as_json:
                put(&self.out, ln, self.lnb.n)
            else:
                put(&self.out, ln + line_at, line_end - line_at)
            put_c(&self.out, 10)
            if self.out.n >= FLUSH_AT:
                self.flush_out()
        at = m.n
        buf_need(m, 31)
        m.n += 31
        self.put_mon_time(m, lt)
        put(m, b'},"level":', 10)
        put_c(m, 51 if warning else 50)  # foxglove.LogLevel WARNING 3, INFO 2
        put(m, b',"message":"', 12)
        put(m, ln + line_at, line_end - line_at)
        put_c(m, 34)
        put_bytes(m, self.monitor_tail(sid))
        put_i(m, index)
        put_c(m, 125)
        put_head(m.p + at, m.n - at - 31, self.ch_monitor, lt)
        if kind == 0:
            self.d_req += 1
        elif kind == 1:
            self.d_resp += 1
        else:
            self.d_exc += 1
        self.mc_span(lt)
        self.rec_ts = ts
        self.rec_any = True
        self.mc_done = m.n
        if m.n >= FLUSH_AT:
            self.flush_mcap()
        if ok and self.left > 0:
            self.left -= 1
            if self.left == 0:
                self.flush_out()
                raise Enough()
        return 0


    # ------------------------------------------------------------------ profiles

    cdef object bound_of(self, int sid, int unit):
        """The :class:`_Bound` of a stream and unit, or None when no profile applies."""
        cdef object key = (<int64_t>sid << 8) | unit
        bound = self.pb.get(key, self)
        if bound is not self:
            return bound
        stream = self.stream_obj(sid)
        profile, session = self.annot.bound(stream, unit)
        bound = None
        if profile is not None:
            shared = (stream.server, unit)
            bound = self.pb_shared.get(shared)
            if bound is None or (<_Bound>bound).profile is not profile:
                bound = _Bound(profile, session)
                (<_Bound>bound).refresh()
                self.pb_shared[shared] = bound
        if len(self.pb) >= 65536:  # bounded: a binding is asked again at no cost to output
            self.pb.clear()
        self.pb[key] = bound
        return bound

    cdef _CRead cread(self, _Bound bound, int fc, int address, int count):
        """The compiled read request shape (made on first use, kept per binding)."""
        cdef object key = (<int64_t>fc << 32) | (<int64_t>address << 16) | count
        cr = bound.reads.get(key)
        if cr is None:
            if len(bound.reads) >= 4096:
                bound.reads.clear()
            cr = bound.reads[key] = _compile_read(bound.profile, fc, address, count,
                                                  self.as_json)
        return <_CRead>cr

    cdef int mark(self, int i, Py_ssize_t at) except -1:
        """Note boundary ``i`` (start, end pairs) is at ``at`` in the output."""
        cdef int cap
        cdef Py_ssize_t* p
        if i >= self.capmarks:
            cap = self.capmarks * 2 if self.capmarks else 512
            while cap <= i:
                cap *= 2
            p = <Py_ssize_t*>realloc(self.marks, cap * sizeof(Py_ssize_t))
            if p == NULL:
                raise MemoryError()
            self.marks = p
            self.capmarks = cap
        self.marks[i] = at
        return 0

    cdef int prof_frame(self, _Bound bound, int64_t index, int sid, int d, double ts,
                        const uint8_t* adu, int alen, Pend* req, double latency) except -1:
        """A frame record under a profile: read requests and answers the compiled read
        covers are written here (with what the session says when it watches the
        answer), every other step goes through the annotator (:meth:`prof_python`)."""
        cdef Native nat, rnat
        cdef bint native
        cdef _CRead cr
        cdef int fc, i, address, count
        session_notes = None
        commands = None
        if self.f_slow:  # --where: every record as the reference's Record
            return self.prof_python(bound, index, sid, d, ts, adu, alen, req, latency)
        if d == 0:
            native = native_pdu(adu + 7, alen - 7, False, NULL, &nat)
        elif req != NULL:
            native = (native_pdu(req.raw + 7, req.alen - 7, False, NULL, &rnat)
                      and native_pdu(adu + 7, alen - 7, True, &rnat, &nat))
        else:
            native = False
        if native and self.fnames[nat.fc] is None:
            native = False
        fc = nat.fc if native else 0
        if native and d == 1 and (fc == 6 or fc == 16):
            return self.prof_write_answer(bound, index, sid, ts, adu, alen, req, latency, &nat,
                                          &rnat)
        if not native or fc < 1 or fc > 4:
            return self.prof_python(bound, index, sid, d, ts, adu, alen, req, latency)
        if d == 0:
            if nat.kind != 0 or (bound.session is not None and ts >= bound.deadline):
                return self.prof_python(bound, index, sid, d, ts, adu, alen, req, latency)
            address = nat.address
            count = nat.count
            cr = self.cread(bound, fc, address, count)
        else:
            if nat.kind != 1 or rnat.kind != 0 or rnat.fc != fc or not rnat.has_addr:
                return self.prof_python(bound, index, sid, d, ts, adu, alen, req, latency)
            address = rnat.address
            count = rnat.count
            cr = self.cread(bound, fc, address, count)
            if cr.nops < 0 or nat.bits or nat.nvalues != count:
                return self.prof_python(bound, index, sid, d, ts, adu, alen, req, latency)
            if bound.session is not None and (
                    ts >= bound.deadline or bound.watched(fc, address, count, nat.vdata)):
                values = tuple([be16(nat.vdata + 2 * i) for i in range(count)])
                session_notes, commands = bound.session.core_answer(
                    fc, address, values, ts, self.stream_obj(sid))
                bound.refresh()
            # a response's address and count are its read request's (the JSON's, the note's)
            nat.has_addr = 1
            nat.address = address
            nat.count = count
        return self.prof_line(sid, d, index, ts, adu, alen, req, latency, &nat, cr,
                              d == 0, d == 1, session_notes, commands)

    cdef int prof_line(self, int sid, int d, int64_t index, double ts, const uint8_t* adu,
                       int alen, Pend* req, double latency, Native* nat, _CRead cr,
                       bint with_notes, bint with_ops, object session_notes,
                       object commands) except -1:
        """A frame's line (and JSON object) with its notes: the generic one, then the
        compiled read's notes (``with_notes``) and its operations on the values
        (``with_ops``), then the session's; then the step's command records."""
        cdef int i, nm
        cdef Py_ssize_t line_at, at, line_end
        cdef Buf* o = &self.out
        cdef int tid = (adu[0] << 8) | adu[1]
        cdef int unit = adu[6]
        cdef int fc = nat.fc
        cdef Py_ssize_t rec_at = o.n
        if self.f_on and not self.f_grep and not self.fast_pass(ts, unit, nat):
            if commands:  # the frame is not shown; its command records are asked alone
                self.command_records(commands)
            return 0
        if self.robot_unsettled or self.labels_missing(sid):
            self.stream_labels(sid)
        cdef bytes label = self.labels[sid][d]
        if self.as_json:
            put(o, b'{"index":', 9)
            put_i(o, index)
            put(o, b',"time":', 8)
            put_json_time(o, ts)
            put_c(o, 44)
            put_bytes(o, self.heads[sid][d])
            put(o, b',"transport":"tcp","tid":', 25)
            put_u(o, tid)
            put(o, b',"unit":', 8)
            put_u(o, unit)
            put(o, b',"fc":', 6)
            put_u(o, fc)
            if nat.kind == 0:
                put_bytes(o, b',"kind":"request","exception_code":null')
            else:
                put_bytes(o, b',"kind":"response","exception_code":null')
            put(o, b',"address":', 11)
            if nat.has_addr:
                put_u(o, nat.address)
            else:
                put(o, b"null", 4)
            put(o, b',"count":', 9)
            if nat.has_addr and nat.count >= 0:
                put_u(o, nat.count)
            else:
                put(o, b"null", 4)
            put(o, b',"values":', 10)
            put_values_json(o, nat)
            put(o, b',"pdu":"', 8)
            put_hex(o, adu + 7, alen - 7)
            put(o, b'","line":"', 10)
        line_at = o.n
        self.put_line_head(o, ts, label, unit, tid, adu, alen)
        nm = 0
        self.mark(nm, o.n)
        self.put_note(nat)
        self.mark(nm + 1, o.n)
        nm += 2
        if with_notes:
            for note in cr.req_notes:
                put(o, b"; ", 2)
                self.mark(nm, o.n)
                put_bytes(o, note)
                self.mark(nm + 1, o.n)
                nm += 2
        if with_ops:
            for i in range(cr.nops):
                put(o, b"; ", 2)
                self.mark(nm, o.n)
                put_op(o, cr, &cr.ops[i], nat.vdata)
                self.mark(nm + 1, o.n)
                nm += 2
        if session_notes:
            for note in session_notes:
                put(o, b"; ", 2)
                self.mark(nm, o.n)
                put_bytes(o, _note_bytes(note, self.as_json))
                self.mark(nm + 1, o.n)
                nm += 2
        if req != NULL:
            put(o, b" (", 2)
            put_double(o, latency * 1000, b'f', 1, 0)
            put(o, b" ms)", 4)
        line_end = o.n
        if self.as_json:
            put(o, b'","notes":[', 11)
            for i in range(0, nm, 2):
                put_c(o, 44 if i else 34)
                if i:
                    put_c(o, 34)
                at = self.marks[i + 1] - self.marks[i]
                buf_need(o, at)
                memcpy(o.p + o.n, o.p + self.marks[i], at)
                o.n += at
                put_c(o, 34)
            put(o, b'],"crc_ok":null,"latency_ms":', 29)
            self.put_json_answer_tail(o, req, latency)
        put_c(o, 10)
        if self.f_on or self.left >= 0:  # its notes are JSON-escaped in a JSON line
            self.selected(rec_at, line_at, line_end, ts, unit, nat, self.as_json)
        if commands:
            self.command_records(commands)
        if o.n >= FLUSH_AT:
            self.flush_out()
        return 0

    cdef int prof_write_answer(self, _Bound bound, int64_t index, int sid, double ts,
                               const uint8_t* adu, int alen, Pend* req, double latency,
                               Native* nat, Native* rnat) except -1:
        """The answer to a register write (FC 06, 10) under a profile: its notes compiled
        (a single write's echo laid out, a multiple write's span), and the session told
        through ``core_write_answer``; the annotator takes it when either cannot."""
        cdef _CRead cr
        cdef int count
        session_notes = None
        commands = None
        if (nat.kind != 1 or rnat.kind != 0 or rnat.fc != nat.fc or not nat.has_addr
                or (bound.session is not None and ts >= bound.deadline)):
            return self.prof_python(bound, index, sid, 1, ts, adu, alen, req, latency)
        count = 1 if nat.fc == 6 else nat.count
        cr = self.cread(bound, nat.fc | 0x100, nat.address, count)
        if cr.nops < 0:
            return self.prof_python(bound, index, sid, 1, ts, adu, alen, req, latency)
        if bound.session is not None:
            key = (req.ts, sid, req.tid, PyBytes_FromStringAndSize(<const char*>req.raw, req.alen))
            done = bound.session.core_write_answer(key, ts, self.stream_obj(sid))
            if done is None:
                return self.prof_python(bound, index, sid, 1, ts, adu, alen, req, latency)
            session_notes, commands = done
            bound.refresh()
        return self.prof_line(sid, 1, index, ts, adu, alen, req, latency, nat, cr, True, True,
                              session_notes, commands)

    cdef int command_records(self, object commands) except -1:
        """The COMMAND records a step made, after its frame's (formatted by mbmon.format)."""
        for cmd in commands:
            rec = Record(self.index, cmd.ts, RecordKind.COMMAND, cmd.stream, command=cmd)
            self.count_record(cmd.ts, cmd.stream.id, False)
            self.cmd_summary.on_records([rec])
            self.put_record(rec)
        return 0

    cdef int prof_python(self, _Bound bound, int64_t index, int sid, int d, double ts,
                         const uint8_t* adu, int alen, Pend* req, double latency) except -1:
        """A frame record the reference way, annotated: its Frame, Transaction and the
        annotator's Annotation, formatted by mbmon.format; then its command records."""
        stream, frame, request, req_index, lat = self.ref_frames(sid, d, ts, adu, alen, req,
                                                                latency)
        pdu = frame.pdu
        if d == 0:
            tx = Transaction(ts, TxStatus.PENDING, frame, None)
        elif req != NULL:
            tx = Transaction(ts, TxStatus.EXCEPTION if pdu.kind is Kind.EXCEPTION
                             else TxStatus.ANSWERED, request, frame, lat)
        else:
            tx = Transaction(ts, TxStatus.UNSOLICITED, None, frame)
        annotation = self.annot.annotate(tx)
        kind = _RECORD_KIND[pdu.kind]
        rec = Record(index, ts, kind, stream, frame, request if d else None, req_index, lat,
                     None, None, None, annotation.notes, annotation.state)
        self.put_record(rec)
        if annotation.commands:
            self.command_records(annotation.commands)
        if bound.session is not None:
            bound.refresh()
        return 0

    def command_counts(self):
        """The summary's robot commands (by outcome) and warnings, or None without a profile."""
        if self.cmd_summary is None:
            return None
        return self.cmd_summary.command_counts(), self.cmd_summary.warnings

    # ------------------------------------------------------------------ pairing

    cdef int pend_slot(self, uint64_t key):
        """The table slot holding ``key``, or the empty slot where it would go (as -1 - slot)."""
        cdef uint64_t mask = (1 << self.tbits) - 1
        cdef uint64_t i = (key * <uint64_t>0x9E3779B97F4A7C15) >> (64 - self.tbits)
        cdef int e
        while True:
            e = self.table[i]
            if e < 0:
                return -1 - <int>i
            if self.pool[e].key == key:
                return <int>i
            i = (i + 1) & mask

    cdef int table_grow(self) except -1:
        cdef int old_bits = self.tbits
        cdef int* old = self.table
        cdef int i, slot
        self.tbits += 1
        self.table = <int*>malloc(sizeof(int) << self.tbits)
        if self.table == NULL:
            self.table = old
            self.tbits = old_bits
            raise MemoryError()
        for i in range(1 << self.tbits):
            self.table[i] = -1
        for i in range(1 << old_bits):
            if old[i] >= 0:
                slot = self.pend_slot(self.pool[old[i]].key)
                self.table[-1 - slot] = old[i]
        free(old)
        return 0

    cdef int table_remove(self, int slot):
        """Backward-shift deletion (linear probing)."""
        cdef uint64_t mask = (1 << self.tbits) - 1
        cdef uint64_t i = slot, j = slot, home
        cdef int e
        while True:
            j = (j + 1) & mask
            e = self.table[j]
            if e < 0:
                break
            home = (self.pool[e].key * <uint64_t>0x9E3779B97F4A7C15) >> (64 - self.tbits)
            # may the entry at j move to i? (home not cyclically in (i, j])
            if (j > i and (home <= i or home > j)) or (j < i and (home <= i and home > j)):
                self.table[i] = e
                i = j
        self.table[i] = -1
        self.tused -= 1
        return 0

    cdef int ensure_stream(self, int sid) except -1:
        cdef int cap, i
        cdef SPend* p
        if sid < self.capsp:
            return 0
        cap = self.capsp * 2 if self.capsp else 64
        while cap <= sid:
            cap *= 2
        p = <SPend*>realloc(self.sp, cap * sizeof(SPend))
        if p == NULL:
            raise MemoryError()
        for i in range(self.capsp, cap):
            p[i].head = -1
            p[i].tail = -1
            p[i].count = 0
            p[i].aprev = -1
            p[i].anext = -1
            p[i].active = False
        self.sp = p
        self.capsp = cap
        return 0

    cdef int new_pend(self) except -1:
        cdef int e, cap
        cdef Pend* p
        if self.free_head >= 0:
            e = self.free_head
            self.free_head = self.pool[e].next
            return e
        if self.npool == self.cappool:
            cap = self.cappool * 2 if self.cappool else 256
            p = <Pend*>realloc(self.pool, cap * sizeof(Pend))
            if p == NULL:
                raise MemoryError()
            self.pool = p
            self.cappool = cap
        e = self.npool
        self.npool += 1
        return e

    cdef int unlink(self, int e) except -1:
        """Take pending request ``e`` out of the table, its stream's list and the pool."""
        cdef Pend* p = &self.pool[e]
        cdef SPend* s = &self.sp[p.sid]
        cdef int slot = self.pend_slot(p.key)
        self.table_remove(slot)
        if p.prev >= 0:
            self.pool[p.prev].next = p.next
        else:
            s.head = p.next
        if p.next >= 0:
            self.pool[p.next].prev = p.prev
        else:
            s.tail = p.prev
        s.count -= 1
        self.total -= 1
        if s.count == 0:  # the pairer deletes an emptied stream's dict
            s.active = False
            if s.aprev >= 0:
                self.sp[s.aprev].anext = s.anext
            else:
                self.ahead = s.anext
            if s.anext >= 0:
                self.sp[s.anext].aprev = s.aprev
            else:
                self.atail = s.aprev
            s.aprev = -1
            s.anext = -1
        p.next = self.free_head
        self.free_head = e
        return 0

    cdef int timeout_record(self, double ts, int e) except -1:
        """A request that got no answer: its TIMEOUT event, then it is forgotten."""
        cdef Pend* p = &self.pool[e]
        info = {"request_index": p.index, "unit": p.unit, "fc": p.fc, "tid": p.tid}
        sid = p.sid
        self.unlink(e)
        return self.event(ts, sid, EventKind.TIMEOUT, info)

    cdef inline double due_by(self, int e, double now) noexcept:
        """The time of request ``e``'s TIMEOUT decided at ``now``: when its answer was
        due (its time plus the timeout), or ``now`` if that came first -- the pairer's
        ``min(req.ts + timeout, now)``, NaN and ties included."""
        cdef double due = self.pool[e].ts + self.timeout
        return now if now < due else due

    cdef int pair_tick(self, double now) except -1:
        cdef double limit = now - self.timeout
        cdef int s = self.ahead, nxt, e
        while s >= 0:
            nxt = self.sp[s].anext
            while self.sp[s].count:
                e = self.sp[s].head
                if self.pool[e].ts > limit:
                    break
                self.timeout_record(self.due_by(e, now), e)
            s = nxt
        return 0

    cdef int on_frame(self, int ci, int d, double ts, const uint8_t* adu, int alen) except -1:
        cdef int sid = self.conns[ci].sid
        cdef int tid = (adu[0] << 8) | adu[1]
        cdef int unit = adu[6]
        cdef int fc = adu[7] & 0x7F
        cdef uint64_t key = (<uint64_t>sid << 24) | (<uint64_t>tid << 8) | <uint64_t>unit
        cdef int slot, e
        cdef SPend* s
        cdef Pend* p
        self.frames += 1
        self.ensure_stream(sid)
        slot = self.pend_slot(key)
        if d == 0:
            if slot >= 0:  # the same (tid, unit) again: the old request times out
                e = self.table[slot]
                self.timeout_record(self.due_by(e, ts), e)
            if adu[7] == 0x08 and alen >= 10 and adu[8] == 0 and adu[9] == 0x04:
                # Diagnostics 04 (Force Listen Only Mode) is never answered: the
                # pairer does not hold it (``expects_reply``), so it never times out
                return self.frame_record(sid, 0, ts, adu, alen, NULL)
            if self.sp[sid].count >= MAX_PENDING_STREAM or self.total >= MAX_PENDING_TOTAL:
                raise Declined("more requests pending than the core keeps")
            e = self.new_pend()
            p = &self.pool[e]
            p.ts = ts
            p.index = self.index
            p.key = key
            p.sid = sid
            p.tid = tid
            p.unit = unit
            p.fc = fc
            p.alen = alen
            memcpy(p.raw, adu, alen)
            s = &self.sp[sid]
            if not s.active:
                s.active = True
                s.aprev = self.atail
                s.anext = -1
                if self.atail >= 0:
                    self.sp[self.atail].anext = sid
                else:
                    self.ahead = sid
                self.atail = sid
            p.prev = s.tail
            p.next = -1
            if s.tail >= 0:
                self.pool[s.tail].next = e
            else:
                s.head = e
            s.tail = e
            s.count += 1
            self.total += 1
            if 2 * (self.tused + 1) > (1 << self.tbits):
                self.table_grow()
            slot = self.pend_slot(key)
            self.table[-1 - slot] = e
            self.tused += 1
            return self.frame_record(sid, 0, ts, adu, alen, NULL)
        if slot >= 0 and self.pool[self.table[slot]].fc == fc:
            e = self.table[slot]
            self.frame_record(sid, 1, ts, adu, alen, &self.pool[e])
            self.unlink(e)
            return 0
        return self.frame_record(sid, 1, ts, adu, alen, NULL)

    # ------------------------------------------------------------------ MBAP framing

    cdef Py_ssize_t frames_of(self, int ci, int d, double ts, const uint8_t* p,
                              Py_ssize_t n) except -1:
        """Frame every whole ADU of ``p[:n]``; the offset of the first byte left.
        ``stopped``: framing stopped there at bytes that are no clean MBAP header
        (noise, or length 255): the reference decoder takes the direction from there."""
        cdef Py_ssize_t pos = 0, end
        cdef int length
        self.stopped = False
        while n - pos >= 6:
            if p[pos + 2] == 0 and p[pos + 3] == 0:
                length = (p[pos + 4] << 8) | p[pos + 5]
                if 2 <= length <= 254:
                    end = pos + 6 + length
                    if end > n:
                        break
                    self.on_frame(ci, d, ts, p + pos, 6 + length)
                    pos = end
                    continue
            self.stopped = True
            break
        return pos

    cdef int on_chunk(self, int ci, int d, double ts, const uint8_t* p,
                      Py_ssize_t n) except -1:
        cdef Half* h = &self.conns[ci].h[d]
        cdef Py_ssize_t pos, old
        self.last_ts = ts
        self.pl_last = ts
        self.batch += 1  # the records of one chunk are one batch (the hub's)
        if self.open_streams < 0:
            self.open_streams = len(self._sid_conn)
        if ts >= self.next_tick:
            # the pipeline ticks the pairer before it decodes the chunk: requests due
            # before it are reported first, and an answer in it after the timeout is late
            self.next_tick = ts + TICK_EVERY
            self.pair_tick(ts)
        if h.dstate != 1:
            if h.dstate == 0:  # the pipeline makes this direction's decoder now
                self.new_dec(ci, d)
            else:
                return self.ref_chunk(ci, d, ts, p, n)
        if h.blen == 0:
            pos = self.frames_of(ci, d, ts, p, n)
            if pos == n:
                return 0
            if self.stopped:
                return self.ref_chunk(ci, d, ts, p + pos, n - pos)
            self.hold(ci, d, p + pos, n - pos)
            self.conns[ci].h[d].bts = ts
        else:
            old = h.blen
            self.hold(ci, d, p, n)
            h = &self.conns[ci].h[d]
            pos = self.frames_of(ci, d, ts, h.buf, h.blen)
            h = &self.conns[ci].h[d]
            if self.stopped:
                # held bytes of 6 or more start a header, so framing stopped in this
                # chunk's bytes, or at the start of fewer held ones (kept, with their time)
                if pos < old:
                    h.blen = <int>old
                    return self.ref_chunk(ci, d, ts, p, n)
                h.blen = 0
                return self.ref_chunk(ci, d, ts, p + (pos - old), n - (pos - old))
            if pos:
                memmove(h.buf, h.buf + pos, h.blen - pos)
                h.blen -= <int>pos
                if pos >= old:
                    h.bts = ts
        return 0

    cdef int new_dec(self, int ci, int d) except -1:
        """The pipeline makes direction ``d``'s decoder (its first bytes): kept in order
        (the pipeline's finish flushes its decoders in the order they were made)."""
        self.conns[ci].h[d].dstate = 1
        self.dec_order.append(ci * 2 + d)
        return 0

    # ------------------------------------------------------------------ noise (the reference)
    #
    # Bytes that are no clean MBAP header (noise, its resynchronisation, length 255) and
    # an incomplete ADU at a stream's end are rare: the direction is framed by the
    # reference's own MbapDecoder from there (made with the bytes the core held, at the
    # time they arrived), its frames paired and written by the core, its noise records
    # formatted by mbmon.format. Once the decoder is in sync again with no noise run
    # open, the core frames the direction again from the bytes the decoder holds.

    cdef object ref_decoder(self, int ci, int d):
        """The reference decoder of direction ``d``: the one framing it, or a new one
        holding the bytes the core holds (they arrived at ``bts``; nothing frames)."""
        cdef Half* h = &self.conns[ci].h[d]
        cdef int key = ci * 2 + d
        if h.dstate == 2:
            return self.mdecs[key]
        dec = MbapDecoder(self.stream_obj(self.conns[ci].sid),
                          Direction.S2C if d else Direction.C2S, silence=self.timeout)
        h = &self.conns[ci].h[d]
        if h.blen:
            dec.feed(PyBytes_FromStringAndSize(<const char*>h.buf, h.blen), h.bts)
            h.blen = 0
        h.dstate = 2
        self.mdecs[key] = dec
        return dec

    cdef int ref_chunk(self, int ci, int d, double ts, const uint8_t* p,
                       Py_ssize_t n) except -1:
        """A chunk's bytes (from the first the core did not frame) through the reference
        decoder (made with the bytes the core holds, which came before them)."""
        data = PyBytes_FromStringAndSize(<const char*>p, n)
        dec = self.ref_decoder(ci, d)
        items = dec.feed(data, ts)
        self.ref_resync(ci, d, dec)
        return self.ref_items(ci, d, items)

    cdef int ref_resync(self, int ci, int d, object dec) except -1:
        """Once the reference decoder of direction ``d`` is in sync again with no noise
        run open, the core frames the direction again from the bytes it holds."""
        cdef Half* h
        if dec.synced and not dec._noise:
            h = &self.conns[ci].h[d]
            h.dstate = 1
            del self.mdecs[ci * 2 + d]
            held = dec._buf
            if len(held):
                self.hold(ci, d, held, len(held))
                self.conns[ci].h[d].bts = dec._buf_ts
        return 0

    cdef int ref_items(self, int ci, int d, list items) except -1:
        """The reference decoder's frames (paired here) and noise runs, in order."""
        cdef const uint8_t* raw
        for item in items:
            if isinstance(item, Frame):
                data = item.raw
                raw = data
                self.on_frame(ci, d, item.ts, raw, len(data))
            else:
                self.noise_record(ci, item)
        return 0

    cdef int noise_record(self, int ci, object noise) except -1:
        """A noise run's record (the pipeline's ``_record``), formatted by mbmon.format."""
        cdef int64_t index = self.index
        cdef int sid = self.conns[ci].sid
        self.noise_records += 1
        self.noise_bytes += len(noise.raw)
        self.count_record(noise.ts, sid, False)
        if not self.emit:
            return 0
        return self.put_record(Record(index, noise.ts, RecordKind.NOISE, noise.stream,
                                      noise=noise))

    cdef int flush_dir(self, int ci, int d, double ts) except -1:
        """The decoder of direction ``d`` flushes (its stream ended, or the input):
        an incomplete ADU becomes noise, a resync candidate is judged; it is gone."""
        cdef Half* h = &self.conns[ci].h[d]
        if h.dstate == 0:
            return 0
        if h.dstate == 1 and not h.blen:
            h.dstate = 0
            return 0
        dec = self.ref_decoder(ci, d)
        self.conns[ci].h[d].dstate = 0
        del self.mdecs[ci * 2 + d]
        return self.ref_items(ci, d, dec.flush(ts))

    cdef int close_stream(self, int ci, double ts) except -1:
        """The pipeline's DISCONNECT: the stream's decoders flush (held bytes: noise)."""
        self.flush_dir(ci, 0, ts)
        return self.flush_dir(ci, 1, ts)

    cdef int hold(self, int ci, int d, const uint8_t* p, Py_ssize_t n) except -1:
        cdef Half* h = &self.conns[ci].h[d]
        cdef int cap
        cdef uint8_t* b
        if h.blen + n > 1 << 24:
            raise Declined("an ADU held over more than 16 MiB")
        if h.blen + n > h.bcap:
            cap = h.bcap * 2 if h.bcap else 512
            while cap < h.blen + n:
                cap *= 2
            b = <uint8_t*>realloc(h.buf, cap)
            if b == NULL:
                raise MemoryError()
            h.buf = b
            h.bcap = cap
        memcpy(h.buf + h.blen, p, n)
        h.blen += <int>n
        return 0

    # ------------------------------------------------------------------ TCP

    cdef int new_conn(self, bytes key, const uint8_t* addrs, int sport, int dport, int flags,
                      double ts) except -1:
        """A new IPv4 connection on ``key`` (dissector ``_new_tcp``); returns flow value."""
        return self.open_conn(key, addrs, 4, sport, dport, flags, ts)

    cdef int alloc_conn(self, const uint8_t* addrs, int alen, int sport, int dport,
                        bint sender_client, bint udp=False) except -1:
        """A new flow's entry and stream id (``addrs``: source then destination address,
        ``alen`` bytes each; ``udp``: a UDP pair); its index."""
        cdef int ci, cap, d
        cdef Conn* c
        cdef Conn* nc
        if self.nconns == self.capconns:
            cap = self.capconns * 2 if self.capconns else 64
            nc = <Conn*>realloc(self.conns, cap * sizeof(Conn))
            if nc == NULL:
                raise MemoryError()
            self.conns = nc
            self.capconns = cap
        ci = self.nconns
        self.nconns += 1
        c = &self.conns[ci]
        c.sid = len(self._sid_conn)
        self._sid_conn.append(ci)
        for d in range(2):
            c.h[d].nxt = -1
            c.h[d].isn = -1
            c.h[d].fin = -1
            c.h[d].done = False
            c.h[d].buf = NULL
            c.h[d].blen = 0
            c.h[d].bcap = 0
            c.h[d].bts = 0.0
            c.h[d].dstate = 0
        c.connected = False
        c.closed = False
        c.open_ = False
        c.tref = False
        c.udp = udp
        c.fin_by = 0
        c.alen = alen
        if sender_client:
            memcpy(c.caddr, addrs, alen)
            memcpy(c.saddr, addrs + alen, alen)
            c.cport = sport
            c.sport = dport
        else:
            memcpy(c.caddr, addrs + alen, alen)
            memcpy(c.saddr, addrs, alen)
            c.cport = dport
            c.sport = sport
        return ci

    cdef int open_conn(self, bytes key, const uint8_t* addrs, int alen, int sport, int dport,
                       int flags, double ts) except -1:
        """A new connection on ``key`` (dissector ``_new_tcp``); returns flow value."""
        cdef bint src_in = self.port_map[sport], dst_in = self.port_map[dport]
        cdef bint sender_client
        cdef int ci
        if src_in and dst_in:
            if flags & (SYN | ACK) == SYN:
                sender_client = True
            elif flags & (SYN | ACK) == (SYN | ACK):
                sender_client = False
            else:
                sender_client = dport <= sport
        else:
            sender_client = dst_in
        if self.nopen >= MAX_OPEN:
            raise Declined("more open connections than the core keeps")
        ci = self.alloc_conn(addrs, alen, sport, dport, sender_client)
        self.conns[ci].open_ = True
        self.open_order.append(ci)
        self.nopen += 1
        rkey = bytes(addrs[alen:2 * alen]) + bytes(addrs[0:alen]) + bytes(
            ((dport >> 8, dport & 255, sport >> 8, sport & 255)))
        self.flows[key] = ci * 2 + (1 if sender_client else 0)
        self.flows[rkey] = ci * 2 + (0 if sender_client else 1)
        self.clear_cache()
        return ci * 2 + (1 if sender_client else 0)

    cdef int clear_cache(self) except -1:
        cdef int i
        for i in range(64):
            self.cval[i] = -1
        return 0

    cdef int forget(self, int ci) except -1:
        """Drop a connection's two keys (unless a newer connection took them)."""
        cdef Conn* c = &self.conns[ci]
        k1 = bytes(c.caddr[:c.alen]) + bytes(c.saddr[:c.alen]) + bytes(
            (c.cport >> 8, c.cport & 255, c.sport >> 8, c.sport & 255))
        k2 = bytes(c.saddr[:c.alen]) + bytes(c.caddr[:c.alen]) + bytes(
            (c.sport >> 8, c.sport & 255, c.cport >> 8, c.cport & 255))
        for k in (k1, k2):
            v = self.flows.get(k)
            if v is not None and v // 2 == ci:
                del self.flows[k]
        self.clear_cache()
        return 0

    cdef int closed_conn(self, int ci, double ts) except -1:
        """Watcher ``closed``: the connection leaves the open ones; its keys linger."""
        cdef Conn* c = &self.conns[ci]
        c.closed = True
        if not c.open_:
            return 0
        c.open_ = False
        self.nopen -= 1
        until = ts + CLOSED_LINGER
        if not self.closed_fifo and until < self.due:
            self.due = until
        self.closed_fifo.append([ci, until])
        if len(self.closed_fifo) > MAX_CLOSED:
            old = self.closed_fifo.pop(0)
            self.forget(old[0])
        return 0

    cdef int dissector_tick(self, double now) except -1:
        """The dissector's ``_tick`` for files: closed connections whose linger ended."""
        fifo = self.closed_fifo
        while fifo:
            if fifo[0][1] > now:
                break
            old = fifo.pop(0)
            self.forget(old[0])
        self.due = fifo[0][1] if fifo else float("inf")
        return 0

    cdef bint is_new(self, int ci, bint from_client, int64_t seq, int flags,
                     bint has_payload) except -1:
        cdef Conn* c = &self.conns[ci]
        if c.tref:
            return self.pyconns[ci].is_new(from_client, seq, flags, has_payload)
        cdef Half* half = &c.h[0 if from_client else 1]
        cdef Half* other = &c.h[1 if from_client else 0]
        cdef int syn_ack = flags & (SYN | ACK)
        if syn_ack == SYN:
            if c.closed:
                return True
            if half.isn < 0:
                return half.nxt >= 0 or other.nxt >= 0
            return seq != half.isn
        if syn_ack == (SYN | ACK):
            return c.closed or (half.isn >= 0 and seq != half.isn)
        if c.closed and has_payload:
            return half.nxt < 0 or abs(signed32(seq - half.nxt)) > REUSE_DISTANCE
        return False

    cdef int acked(self, int ci, int d, double ts, int64_t ack) except -1:
        """The peer acknowledged bytes this direction never showed (``_acked``): they
        were lost by the capture, a GAP (``acked-unseen``) skips them. Here nothing is
        held behind a hole and a FIN seen is reached: the GAP runs up to ``ack``."""
        cdef Half* other = &self.conns[ci].h[d]
        cdef int64_t diff
        if other.nxt >= 0 and not other.done:
            diff = (ack - other.nxt) & MASK
            if 0 < diff <= MAX_ACK_JUMP:
                other.nxt = ack & MASK
                self.gap(ci, d, ts, diff, "acked-unseen")
        return 0

    cdef int gap(self, int ci, int d, double ts, int64_t missing, str reason) except -1:
        """A GAP event of direction ``d``: the pipeline resets the direction's decoder
        (what it held is noise), then the event's record."""
        self.reset_dir(ci, d, ts)
        return self.event(ts, self.conns[ci].sid, EventKind.GAP,
                          {"direction": "s2c" if d else "c2s", "bytes": missing,
                           "reason": reason})

    cdef int reset_dir(self, int ci, int d, double ts) except -1:
        """The decoder of direction ``d`` resets (a gap): held bytes and the noise run
        become noise ("discarded after gap"); the next bytes start an ADU."""
        cdef Half* h = &self.conns[ci].h[d]
        if h.dstate == 0 or (h.dstate == 1 and not h.blen):
            return 0
        dec = self.ref_decoder(ci, d)
        items = dec.reset(ts)
        self.conns[ci].h[d].dstate = 1
        del self.mdecs[ci * 2 + d]
        return self.ref_items(ci, d, items)

    # ------------------------------------------------------------------ TCP holes (the reference)
    #
    # A segment that would hold bytes behind a hole (out of order) or meet a FIN ahead
    # of bytes not seen hands its connection to the reference's own TcpConnection
    # (made from the core's state, as the live hand-over makes it); its chunks and
    # events are taken here in order (chunks framed by the core, GAPs resetting the
    # decoder, DISCONNECT closing the stream). Once nothing is held and every FIN
    # seen is reached, the core reassembles the connection again.

    cdef bint needs_ref(self, int ci, int d, int64_t seq, int flags, Py_ssize_t n):
        """Whether ``segment``'s general path would hold this segment's bytes behind a
        hole or set a FIN ahead of bytes not seen (an open connection, no RST)."""
        cdef Half* half = &self.conns[ci].h[d]
        cdef int64_t nxt = half.nxt, diff, after
        if flags & SYN and flags & FIN:
            flags &= ~FIN
        if flags & SYN:
            if half.isn < 0 and nxt < 0:
                nxt = (seq + 1) & MASK
            seq = (seq + 1) & MASK
        elif nxt < 0 and (n or flags & FIN):
            nxt = seq
        if nxt < 0:
            return False
        after = nxt
        if n and not half.done:
            diff = (seq - nxt) & MASK
            if diff == 0:
                after = (nxt + n) & MASK
            elif diff & HALF:
                if TWO32 - diff < n:
                    after = (seq + n) & MASK
            else:
                return True
        if flags & FIN and half.fin < 0 and signed32(after - ((seq + n) & MASK)) < 0:
            return True
        return False

    cdef object hole_watcher(self):
        """The watcher of the connections the reference reassembles (``held`` and
        ``closed``): none for a file (its holes never time out); the live entry's own."""
        return None

    cdef object py_tcp(self, int ci):
        """Connection ``ci`` as the reference's ``TcpConnection`` (its state the core's)."""
        cdef Conn* c = &self.conns[ci]
        cdef int d
        conn = TcpConnection(self.stream_obj(c.sid), limit=_TCP_HOLD_LIMIT, stats=self.tcp_stats,
                             watcher=self.hole_watcher())
        c = &self.conns[ci]
        for d in range(2):
            half = conn._s2c if d else conn._c2s
            half.nxt = None if c.h[d].nxt < 0 else c.h[d].nxt
            half.isn = None if c.h[d].isn < 0 else c.h[d].isn
            half.fin = None if c.h[d].fin < 0 else c.h[d].fin
            half.done = bool(c.h[d].done)
        conn.connected = bool(c.connected)
        conn.closed = bool(c.closed)
        conn.fin_by = None if c.fin_by == 0 else ("client" if c.fin_by == 1 else "server")
        return conn

    cdef int ref_segment(self, int ci, bint from_client, double ts, int64_t seq, int64_t ack,
                         int flags, const uint8_t* p, Py_ssize_t n) except -1:
        """One segment of a connection the reference reassembles (made so now if not)."""
        cdef Conn* c
        cdef int d
        conn = self.pyconns.get(ci)
        if conn is None:
            conn = self.pyconns[ci] = self.py_tcp(ci)
            self.conns[ci].tref = True
            # the reference's state is the connection's now: the core's halves say
            # "none" (-2: no sequence number), so the core's fast path never takes it
            self.conns[ci].h[0].nxt = -2
            self.conns[ci].h[1].nxt = -2
        out = []
        conn.segment(ts, from_client, seq & MASK, ack & MASK, flags,
                     PyBytes_FromStringAndSize(<const char*>p, n) if n else b"", out)
        self.ref_out(ci, out)
        return self.ref_done(ci)

    cdef int ref_done(self, int ci) except -1:
        """Once the reference's reassembly of connection ``ci`` holds nothing and has
        reached every FIN it saw, the core reassembles the connection again."""
        cdef Conn* c
        cdef int d
        conn = self.pyconns.get(ci)
        if conn is None:
            return 0
        for half in (conn._c2s, conn._s2c):
            if half.held or (half.fin is not None and not half.done):
                return 0
        # nothing held, every FIN seen reached: the core reassembles it again
        c = &self.conns[ci]
        for d in range(2):
            half = conn._s2c if d else conn._c2s
            c.h[d].nxt = -1 if half.nxt is None else half.nxt
            c.h[d].isn = -1 if half.isn is None else half.isn
            c.h[d].fin = -1 if half.fin is None else half.fin
            c.h[d].done = half.done
        c.connected = conn.connected
        c.fin_by = 0 if conn.fin_by is None else (1 if conn.fin_by == "client" else 2)
        c.tref = False
        del self.pyconns[ci]
        return 0

    cdef int ref_out(self, int ci, list out) except -1:
        """The chunks and events of the reference's reassembly, as the pipeline takes
        them (and the dissector's watcher: a DISCONNECT closes the connection)."""
        cdef int sid = self.conns[ci].sid, d
        cdef const uint8_t* b
        for item in out:
            if type(item) is Chunk:
                d = 1 if item.direction is Direction.S2C else 0
                data = item.data
                b = data
                if self.mcap is not None:
                    self.mcap_chunk(sid, d, item.ts, b, len(data))
                self.on_chunk(ci, d, item.ts, b, len(data))
                continue
            kind = item.kind
            if kind is EventKind.GAP:
                self.gap(ci, 1 if item.info["direction"] == "s2c" else 0, item.ts,
                         item.info["bytes"], item.info["reason"])
            elif kind is EventKind.DISCONNECT:
                self.event(item.ts, sid, kind, item.info)
                self.close_stream(ci, item.ts)
                self.closed_conn(ci, item.ts)
            else:
                self.event(item.ts, sid, kind, item.info or None)
        return 0

    cdef int ref_finish(self, int ci, double ts, str reason) except -1:
        """The reference's ``finish`` of a connection it reassembles (the end of the
        capture, or its addresses taken by a new connection)."""
        conn = self.pyconns.pop(ci, None)
        if conn is None:
            return 0
        self.conns[ci].tref = False
        out = []
        conn.finish(ts, out, reason)
        return self.ref_out(ci, out)

    cdef int deliver(self, int ci, int d, double ts, const uint8_t* p, Py_ssize_t n) except -1:
        self.conns[ci].h[d].nxt = (self.conns[ci].h[d].nxt + n) & MASK
        if self.mcap is not None:  # the chunk on /modbus/raw, before the records it makes
            self.mcap_chunk(self.conns[ci].sid, d, ts, p, n)
        return self.on_chunk(ci, d, ts, p, n)

    cdef int data(self, int ci, int d, double ts, int64_t seq, const uint8_t* p,
                  Py_ssize_t n) except -1:
        cdef Half* h = &self.conns[ci].h[d]
        cdef int64_t diff = (seq - h.nxt) & MASK
        cdef int64_t old
        if diff == 0:
            return self.deliver(ci, d, ts, p, n)
        if diff & HALF:
            old = TWO32 - diff
            if old >= n:
                return 0  # a retransmission: counted by the dissector, dropped
            return self.deliver(ci, d, ts, p + old, n - old)
        raise Declined("out-of-order TCP segments (held behind a hole)")

    cdef int segment(self, int ci, bint from_client, double ts, int64_t seq, int64_t ack,
                     int flags, const uint8_t* p, Py_ssize_t n) except -1:
        """``TcpConnection.segment``: the core's own reassembly while nothing is held
        behind a hole; the reference's (``ref_segment``) from a segment that would be."""
        cdef Conn* c = &self.conns[ci]
        cdef int d = 0 if from_client else 1
        cdef Half* half = &c.h[d]
        cdef Half* other = &c.h[1 - d]
        if not flags & 0x07 and half.nxt == seq and half.fin < 0:
            if c.closed:
                return 0  # payload after the end: counted and dropped (after_close)
            if flags & ACK:
                self.acked(ci, 1 - d, ts, ack)
            if n:
                self.deliver(ci, d, ts, p, n)
            return 0
        if c.tref:  # (its halves' nxt is -2: never the fast path above)
            return self.ref_segment(ci, from_client, ts, seq, ack, flags, p, n)
        if c.closed:
            return 0  # payload after the end: counted and dropped
        if not flags & RST and self.needs_ref(ci, d, seq, flags, n):
            return self.ref_segment(ci, from_client, ts, seq, ack, flags, p, n)
        if flags & RST:
            if (half.fin >= 0 and not half.done) or (other.fin >= 0 and not other.done):
                raise Declined("a reset before a FIN was reached (a gap)")
            self.event(ts, c.sid, EventKind.DISCONNECT,
                       {"how": "rst", "by": "client" if from_client else "server"})
            self.close_stream(ci, ts)
            self.closed_conn(ci, ts)
            return 0
        if flags & SYN and flags & FIN:
            flags &= ~FIN
        if flags & SYN:
            if half.isn < 0 and half.nxt < 0:
                half.isn = seq & MASK
                half.nxt = (seq + 1) & MASK
            if not c.connected:
                c.connected = True
                self.event(ts, c.sid, EventKind.CONNECT, None)
            seq = (seq + 1) & MASK
        elif half.nxt < 0 and (n or flags & FIN):
            half.nxt = seq
        if flags & ACK:
            self.acked(ci, 1 - d, ts, ack)
        c = &self.conns[ci]
        half = &c.h[d]
        other = &c.h[1 - d]
        if n and half.nxt >= 0:
            if not half.done:  # else: after its direction's FIN, counted and dropped
                self.data(ci, d, ts, seq, p, n)
                c = &self.conns[ci]
                half = &c.h[d]
                other = &c.h[1 - d]
        if flags & FIN and half.fin < 0 and half.nxt >= 0:
            half.fin = (seq + n) & MASK
            if c.fin_by == 0:
                c.fin_by = 1 if from_client else 2
            if signed32(half.nxt - half.fin) < 0:
                raise Declined("a FIN ahead of bytes not seen (a gap)")
            if not half.done:
                half.done = True
                half.nxt = (half.fin + 1) & MASK
                if other.done and not c.closed:
                    self.event(ts, c.sid, EventKind.DISCONNECT,
                               {"how": "fin", "by": "client" if c.fin_by == 1 else "server"})
                    self.close_stream(ci, ts)
                    self.closed_conn(ci, ts)
        return 0

    # ------------------------------------------------------------------ packets

    cdef int packet(self, double ts, int link, const uint8_t[::1] buf, Py_ssize_t off,
                    Py_ssize_t end) except -1:
        """``Dissector.packet`` for the link types and IPv4/TCP the core covers."""
        cdef int et, vihl, ihl, proto, sport, dport, doff, flags, family, i, v
        cdef Py_ssize_t total, ip_end, l4
        cdef int64_t seq, ack
        cdef const uint8_t* b
        cdef bint from_client, first_fragment
        cdef uint8_t kb[12]
        cdef uint32_t slot
        if ts >= self.due:
            self.dissector_tick(ts)
        if end <= off:
            if link in (1, 113, 276, 0, 108, 101, 12, 14, 228, 229):
                return 0  # truncated: counted, skipped
            if link < 0:
                return 0
            raise Declined("link type %d" % link)
        b = &buf[off]
        if link == 1:
            if end - off < 14:
                return 0
            et = (b[12] << 8) | b[13]
            off += 14
        elif link == 113:
            if end - off < 16:
                return 0
            et = (b[14] << 8) | b[15]
            off += 16
        elif link == 276:
            if end - off < 20:
                return 0
            et = (b[0] << 8) | b[1]
            off += 20
        elif link == 101 or link == 12 or link == 14:
            v = b[0] >> 4
            et = 0x0800 if v == 4 else (0x86DD if v == 6 else 0)
        elif link == 0 or link == 108:
            if end - off < 4:
                return 0
            family = <int>le32(b)
            if <uint32_t>le32(b) > 0xFFFF:
                family = <int>be32(b)
            et = 0x0800 if family == 2 else (
                0x86DD if family in (10, 23, 24, 28, 30) else 0)
            off += 4
        elif link == 228:
            et = 0x0800
        elif link == 229:
            et = 0x86DD
        elif link < 0:
            return 0
        else:
            raise Declined("link type %d" % link)
        while et == 0x8100 or et == 0x88A8 or et == 0x9100:
            if end - off < 4:
                return 0
            et = (buf[off + 2] << 8) | buf[off + 3]
            off += 4
        if et == 0x86DD:
            return self.ipv6(ts, buf, off, end)
        if et != 0x0800:
            return 0
        if end - off < 20:
            return 0
        b = &buf[off]
        vihl = b[0]
        ihl = (vihl & 15) << 2
        if vihl >> 4 != 4 or ihl < 20:
            return 0
        total = (b[2] << 8) | b[3]
        if total == 0:
            ip_end = end
        elif total < ihl:
            return 0
        else:
            ip_end = off + total
            if ip_end > end:
                ip_end = end
        first_fragment = False
        if ((b[6] << 8) | b[7]) & 0x3FFF:
            if ((b[6] << 8) | b[7]) & 0x1FFF:
                return 0  # not the first fragment: no transport header
            first_fragment = True
        proto = b[9]
        l4 = off + ihl
        if proto == 17:
            if ip_end - l4 >= 8:
                self.good_ts = ts
                sport = (buf[l4] << 8) | buf[l4 + 1]
                dport = (buf[l4 + 2] << 8) | buf[l4 + 3]
                if self.port_map[sport] or self.port_map[dport]:
                    # a first fragment is a cut packet (the reference does not
                    # reassemble): a datagram longer than it is none
                    return self.udp_datagram(ts, &buf[off + 12], 4, buf, l4, ip_end)
                self.other_port(UDP_PORT_KEY | (sport if sport < dport else dport))
            return 0
        if proto != 6:
            return 0
        if ip_end - l4 < 20:
            return 0
        self.good_ts = ts
        b = &buf[l4]
        sport = (b[0] << 8) | b[1]
        dport = (b[2] << 8) | b[3]
        if not self.port_map[sport] and not self.port_map[dport]:
            doff = (b[12] >> 2) & 0x3C
            if self.detect and not first_fragment and not (total and off + total > end) and (
                    20 <= doff <= ip_end - l4):
                self.detect_segment(ts, bytes(buf[off + 12:off + 20]), sport, dport,
                                    be32(b + 4), be32(b + 8), b[13],
                                    bytes(buf[l4 + doff:ip_end]))
            else:
                self.other_port(sport if sport < dport else dport)
            return 0
        # a first fragment is a cut packet (the reference does not reassemble): its
        # segment carries the bytes the fragment holds, as a snap-cut one does
        doff = (b[12] >> 2) & 0x3C
        if doff < 20 or l4 + doff > ip_end:
            return 0
        seq = be32(b + 4)
        ack = be32(b + 8)
        flags = b[13]
        memcpy(kb, &buf[off + 12], 8)
        kb[8] = sport >> 8
        kb[9] = sport & 255
        kb[10] = dport >> 8
        kb[11] = dport & 255
        slot = (be32(kb) * 31 + be32(kb + 4) * 17 + <uint32_t>sport * 7 + <uint32_t>dport) & 63
        if self.cval[slot] >= 0 and memcmp(self.ckey[slot], kb, 12) == 0:
            v = self.cval[slot]
        else:
            key = PyBytes_FromStringAndSize(<const char*>kb, 12)
            got = self.flows.get(key)
            v = -1 if got is None else got
        if v < 0 or flags & SYN or self.conns[v >> 1].closed:
            key = PyBytes_FromStringAndSize(<const char*>kb, 12)
            v = self.tcp_flow(key, &buf[off + 12], v, ts, seq, flags, ip_end > l4 + doff,
                              sport, dport)
        memcpy(self.ckey[slot], kb, 12)
        self.cval[slot] = v
        from_client = v & 1
        if ip_end > l4 + doff:
            return self.segment(v >> 1, from_client, ts, seq, ack, flags, &buf[l4 + doff],
                                ip_end - (l4 + doff))
        return self.segment(v >> 1, from_client, ts, seq, ack, flags, NULL, 0)

    cdef int tcp_flow(self, bytes key, const uint8_t* addrs, int v, double ts, int64_t seq,
                      int flags, bint has_payload, int sport, int dport,
                      int alen=4) except -1:
        cdef int ci
        if v < 0:
            if alen != 4:
                return self.open_conn(key, addrs, alen, sport, dport, flags, ts)
            return self.new_conn(key, addrs, sport, dport, flags, ts)
        ci = v >> 1
        if (flags & SYN or self.conns[ci].closed) and self.is_new(ci, v & 1, seq, flags,
                                                                   has_payload):
            if not self.conns[ci].closed:
                # replaced while open: the reference gives its holes up ("replaced")
                # and forgets it (no DISCONNECT; its stream's decoders live on)
                self.ref_finish(ci, ts, "replaced")
                if not self.conns[ci].closed and self.conns[ci].open_:
                    self.conns[ci].open_ = False
                    self.nopen -= 1
            # the old connection is forgotten (a closed one's linger ends)
            for i, item in enumerate(self.closed_fifo):
                if item[0] == ci:
                    del self.closed_fifo[i]
                    break
            self.forget(ci)
            if alen != 4:
                return self.open_conn(key, addrs, alen, sport, dport, flags, ts)
            return self.new_conn(key, addrs, sport, dport, flags, ts)
        return v

    cdef int ipv6(self, double ts, const uint8_t[::1] buf, Py_ssize_t off,
                  Py_ssize_t end) except -1:
        """IPv6 (``ipv6_header``: extension headers as the reference walks them): TCP and
        UDP on a Modbus port are read as over IPv4 (a first fragment as a cut packet); TCP on
        other ports goes to port detection as the reference's general path sends it."""
        cdef Py_ssize_t ip_end, l4, plen
        cdef int proto, k, sport, dport, doff, frag
        cdef bint short = False, fragment = False
        if end - off < 40 or buf[off] >> 4 != 6:
            return 0
        plen = (buf[off + 4] << 8) | buf[off + 5]
        ip_end = off + 40 + plen if plen else end
        if ip_end > end:
            short = True
            ip_end = end
        proto = buf[off + 6]
        l4 = off + 40
        for k in range(16):
            if proto in (0, 43, 60, 135, 139, 140, 253, 254):
                if ip_end - l4 < 8:
                    return 0
                proto, l4 = buf[l4], l4 + ((buf[l4 + 1] + 1) << 3)
            elif proto == 44:
                if ip_end - l4 < 8:
                    return 0
                frag = (buf[l4 + 2] << 8) | buf[l4 + 3]
                if frag & 0xFFF9:
                    if frag & 0xFFF8:
                        return 0  # not the first fragment: no transport header
                    fragment = True
                proto, l4 = buf[l4], l4 + 8
            elif proto == 51:
                if ip_end - l4 < 8:
                    return 0
                proto, l4 = buf[l4], l4 + ((buf[l4 + 1] + 2) << 2)
            else:
                break
        if proto == 17 and ip_end - l4 >= 8:
            self.good_ts = ts
            sport = (buf[l4] << 8) | buf[l4 + 1]
            dport = (buf[l4 + 2] << 8) | buf[l4 + 3]
            if self.port_map[sport] or self.port_map[dport]:  # a first fragment: cut
                return self.udp_datagram(ts, &buf[off + 8], 16, buf, l4, ip_end)
            self.other_port(UDP_PORT_KEY | (sport if sport < dport else dport))
            return 0
        if proto != 6 or ip_end - l4 < 20:
            return 0
        self.good_ts = ts
        sport = (buf[l4] << 8) | buf[l4 + 1]
        dport = (buf[l4 + 2] << 8) | buf[l4 + 3]
        if self.port_map[sport] or self.port_map[dport]:  # a first fragment: cut
            return self.tcp6(ts, buf, off, l4, ip_end)
        doff = (buf[l4 + 12] >> 2) & 0x3C
        if self.detect and not short and not fragment and 20 <= doff <= ip_end - l4:
            self.detect_segment(ts, bytes(buf[off + 8:off + 40]), sport, dport,
                                be32(&buf[l4 + 4]), be32(&buf[l4 + 8]), buf[l4 + 13],
                                bytes(buf[l4 + doff:ip_end]))
        else:
            self.other_port(sport if sport < dport else dport)
        return 0

    cdef int tcp6(self, double ts, const uint8_t[::1] buf, Py_ssize_t off, Py_ssize_t l4,
                  Py_ssize_t ip_end) except -1:
        """A TCP segment over IPv6 on a Modbus port (its addresses at ``off + 8``): the
        flow table and reassembly as over IPv4 (36-byte flow keys, no cache)."""
        cdef const uint8_t* b = &buf[l4]
        cdef int sport = (b[0] << 8) | b[1], dport = (b[2] << 8) | b[3]
        cdef int doff = (b[12] >> 2) & 0x3C, flags, v
        cdef int64_t seq, ack
        if doff < 20 or l4 + doff > ip_end:
            return 0
        seq = be32(b + 4)
        ack = be32(b + 8)
        flags = b[13]
        key = bytes(buf[off + 8:off + 40]) + bytes(buf[l4:l4 + 4])
        got = self.flows.get(key)
        v = -1 if got is None else got
        if v < 0 or flags & SYN or self.conns[v >> 1].closed:
            v = self.tcp_flow(key, &buf[off + 8], v, ts, seq, flags, ip_end > l4 + doff,
                              sport, dport, 16)
        if ip_end > l4 + doff:
            return self.segment(v >> 1, v & 1, ts, seq, ack, flags, &buf[l4 + doff],
                                ip_end - (l4 + doff))
        return self.segment(v >> 1, v & 1, ts, seq, ack, flags, NULL, 0)

    # ------------------------------------------------------------------ UDP

    cdef int udp_datagram(self, double ts, const uint8_t* addrs, int alen,
                          const uint8_t[::1] buf, Py_ssize_t l4, Py_ssize_t ip_end) except -1:
        """A UDP datagram on a Modbus port (``_udp_general``): one chunk of its pair's
        stream, framed and then flushed at once (``datagram`` decoding: nothing of it
        waits for the next one). Its frames are written the reference way."""
        cdef int sport = (buf[l4] << 8) | buf[l4 + 1], dport = (buf[l4 + 2] << 8) | buf[l4 + 3]
        cdef Py_ssize_t ulen = (buf[l4 + 4] << 8) | buf[l4 + 5]
        cdef bint sender_client
        cdef int ci, d
        if ulen < 8 or l4 + ulen > ip_end or ulen == 8:
            return 0  # malformed, cut (half a datagram is none), or empty
        key = bytes(addrs[:2 * alen]) + bytes(buf[l4:l4 + 4])
        got = self.udp_pairs.get(key)
        if got is None:
            if len(self.udp_pairs) >= 2 * MAX_UDP:
                raise Declined("more UDP pairs than the core keeps")
            # _roles(key, 0): the endpoint on a Modbus port is the server (both: the
            # lower port, else the receiver)
            if self.port_map[sport] and self.port_map[dport]:
                sender_client = dport <= sport
            else:
                sender_client = self.port_map[dport]
            ci = self.alloc_conn(addrs, alen, sport, dport, sender_client, True)
            got = ci * 2 + (1 if sender_client else 0)
            self.udp_pairs[key] = got
            self.udp_pairs[bytes(addrs[alen:2 * alen]) + bytes(addrs[:alen]) + bytes(
                buf[l4 + 2:l4 + 4]) + bytes(buf[l4:l4 + 2])] = ci * 2 + (
                0 if sender_client else 1)
        ci = got >> 1
        d = 0 if got & 1 else 1
        if self.mcap is not None:
            self.mcap_chunk(self.conns[ci].sid, d, ts, &buf[l4 + 8], ulen - 8)
        global _ref_lines
        _ref_lines = True  # its frames' lines the reference's ("transport":"udp")
        try:
            self.on_chunk(ci, d, ts, &buf[l4 + 8], ulen - 8)
            # the datagram's end: the decoder flushes (an incomplete ADU, noise) and is
            # as new
            if self.conns[ci].h[d].dstate == 2 or self.conns[ci].h[d].blen:
                dec = self.ref_decoder(ci, d)
                self.conns[ci].h[d].dstate = 1
                del self.mdecs[ci * 2 + d]
                self.ref_items(ci, d, dec.flush(ts))
        finally:
            _ref_lines = False
        return 0

    cdef int other_port(self, int key) except -1:
        """A TCP or UDP packet on no Modbus port that the reference dissector counts for
        the summary's hint (``Dissector._other_port``: ``key`` the lower port, with
        ``UDP_PORT_KEY`` for UDP): nothing for a file (a capture without frames is
        declined); the streaming entry counts them."""
        return 0

    cdef int detect_segment(self, double ts, bytes addrs, int sport, int dport, int64_t seq,
                            int64_t ack, int flags, bytes payload) except -1:
        """A TCP segment on no Modbus port: the reference's port detector judges it
        (the same detector, fed the same segments as the reference dissector feeds
        it). While nothing is found, the reference drops these segments as the core
        does; a connection found to be Modbus is the reference's to read."""
        if self.detector is None:
            return 0
        verdict = self.detector.segment(ts, (addrs, sport, dport), seq, ack, flags, payload)
        if verdict is not True and verdict is not False:
            raise Declined("Modbus found by port detection on a port not named (port %d)"
                           % min(sport, dport))
        return 0

    # ------------------------------------------------------------------ containers

    cdef int run_pcap(self, const uint8_t[::1] data) except -1:
        cdef Py_ssize_t size = data.shape[0], pos = 24, start, caplen
        cdef bint big
        cdef uint32_t magic = le32(&data[0])
        cdef double divisor
        cdef int header = 16, link
        cdef uint32_t snaplen, limit
        cdef double ts = 0.0
        if magic in (0xA1B2C3D4, 0xA1B23C4D, 0xA1B2CD34):
            big = False
        else:
            big = True
            magic = be32(&data[0])
        divisor = 1e9 if magic == 0xA1B23C4D else 1e6
        if magic == 0xA1B2CD34:
            header = 24
        if size < 24 or rd16(&data[4], big) != 2:
            raise Declined("a damaged pcap file header")
        snaplen = rd32(&data[16], big)
        link = rd32(&data[20], big) & 0x0FFFFFFF
        limit = snaplen if snaplen > 262144 else 262144
        if limit > MAX_RECORD:
            limit = MAX_RECORD
        while True:
            if size - pos < header:
                if size == pos:
                    break
                raise Declined("a damaged capture (truncated record header)")
            caplen = rd32(&data[pos + 8], big)
            if caplen > limit:
                raise Declined("a damaged capture (corrupt record header)")
            if pos + header + caplen > size:
                raise Declined("a damaged capture (truncated record)")
            ts = <double>rd32(&data[pos], big) + <double>rd32(&data[pos + 4], big) / divisor
            start = pos + header
            pos = start + caplen
            self.packet(ts, link, data, start, pos)
            if pos - self.released >= RELEASE_EVERY:
                self.release_to(pos)
            if pos >= self.next_progress:
                self.report(pos)
        self.end_ts = ts
        return 0

    cdef int run_pcapng(self, const uint8_t[::1] data) except -1:
        cdef Py_ssize_t size = data.shape[0], pos = 0, blen, end, caplen, start, p
        cdef bint big = False
        cdef uint32_t btype, iface
        cdef uint64_t stamp
        cdef double ts = 0.0
        cdef int code, olen, resol
        cdef list ifaces = []   # (link, divisor, offset, snaplen)
        while True:
            if size - pos < 12:
                if size == pos:
                    break
                raise Declined("a damaged capture (truncated block header)")
            btype = rd32(&data[pos], big)
            if le32(&data[pos]) == 0x0A0D0D0A:
                if be32(&data[pos + 8]) == 0x4D3C2B1A:
                    big = False
                elif be32(&data[pos + 8]) == 0x1A2B3C4D:
                    big = True
                else:
                    raise Declined("a damaged capture (section header)")
                btype = 0x0A0D0D0A
                ifaces = []
            blen = rd32(&data[pos + 4], big)
            if blen < 12 or blen % 4 or blen > MAX_RECORD:
                raise Declined("a damaged capture (block length)")
            if size - pos < blen:
                raise Declined("a damaged capture (truncated block)")
            end = pos + blen - 4
            if rd32(&data[end], big) != <uint32_t>blen:
                raise Declined("a damaged capture (trailing length)")
            if btype == 6 or btype == 2:
                if blen < 32:
                    raise Declined("a damaged capture (packet block)")
                if btype == 6:
                    iface = rd32(&data[pos + 8], big)
                    stamp = (<uint64_t>rd32(&data[pos + 12], big) << 32) | rd32(&data[pos + 16], big)
                    caplen = rd32(&data[pos + 20], big)
                else:
                    iface = rd16(&data[pos + 8], big)
                    stamp = (<uint64_t>rd32(&data[pos + 12], big) << 32) | rd32(&data[pos + 16], big)
                    caplen = rd32(&data[pos + 20], big)
                if pos + 28 + caplen > end:
                    raise Declined("a damaged capture (packet length)")
                if iface < <uint32_t>len(ifaces):
                    self.rec_iface = iface
                    link, div, tsoff, _ = ifaces[iface]
                    if stamp > (<uint64_t>1 << 53) or not -(1 << 53) <= tsoff <= (1 << 53):
                        raise Declined("pcapng timestamps beyond 2^53 units")
                    ts = <double>stamp / <double>div + <double>tsoff
                    self.packet(ts, link, data, pos + 28, pos + 28 + caplen)
                else:
                    self.packet(ts, -1, data, pos, pos)
            elif btype == 3:
                if blen < 16:
                    raise Declined("a damaged capture (simple packet block)")
                caplen = rd32(&data[pos + 8], big)
                if caplen > end - (pos + 12):
                    caplen = end - (pos + 12)
                if ifaces:
                    self.rec_iface = 0
                    link, _, _, snaplen = ifaces[0]
                    if snaplen and caplen > snaplen:
                        caplen = snaplen
                    self.packet(ts, link, data, pos + 12, pos + 12 + caplen)
                else:
                    self.packet(ts, -1, data, pos, pos)
            elif btype == 1:
                if blen < 20:
                    raise Declined("a damaged capture (interface block)")
                link = rd16(&data[pos + 8], big)
                snaplen = rd32(&data[pos + 12], big)
                div = 1000000
                tsoff = 0
                p = pos + 16
                while p + 4 <= end:
                    code = rd16(&data[p], big)
                    olen = rd16(&data[p + 2], big)
                    if code == 0 or p + 4 + olen > end:
                        break
                    if code == 9 and olen >= 1:
                        resol = data[p + 4]
                        div = (2 ** int(resol & 0x7F)) if resol & 0x80 else (
                            10 ** int(min(resol, 30)))
                    elif code == 14 and olen >= 8:
                        tsoff = int.from_bytes(bytes(data[p + 4:p + 12]),
                                               "big" if big else "little", signed=True)
                    p += 4 + olen + (4 - olen % 4) % 4
                if div > (1 << 53) or div == 0:
                    raise Declined("a pcapng timestamp resolution beyond 2^53")
                ifaces.append((link, div, tsoff, snaplen))
            pos += blen
            if pos - self.released >= RELEASE_EVERY:
                self.release_to(pos)
            if pos >= self.next_progress:
                self.report(pos)
        self.end_ts = ts
        return 0

    cdef int report(self, Py_ssize_t pos) except -1:
        """Progress: each of the two passes is half of the work."""
        self.next_progress = pos + (1 << 20)
        if self.progress is not None:
            self.progress(self.progress_base + pos // 2, self.size)
        return 0

    cdef int release_to(self, Py_ssize_t pos) except -1:
        """Give the pages of the file read so far back (peak RSS stays flat in its size);
        nothing points into them any more: held bytes are copies."""
        cdef Py_ssize_t upto = pos - pos % RELEASE_EVERY
        if self.release is not None and upto > self.released:
            self.release(self.released, upto - self.released)
        self.released = upto
        return 0

    cpdef run(self, const uint8_t[::1] data):
        """Every record of the capture ``data``, then the end of input."""
        cdef int ci
        cdef Conn* c
        cdef int s, e, nxt
        self.size = data.shape[0]
        if data.shape[0] < 12:
            raise Declined("a capture too short")
        if le32(&data[0]) == 0x0A0D0D0A:
            self.run_pcapng(data)
        elif le32(&data[0]) in (0xA1B2C3D4, 0xA1B23C4D, 0xA1B2CD34) or be32(&data[0]) in (
                0xA1B2C3D4, 0xA1B23C4D, 0xA1B2CD34):
            self.run_pcap(data)
        else:
            raise Declined("a container other than pcap and pcapng")
        # the dissector's finish: half-closed connections end
        for ci in self.open_order:
            c = &self.conns[ci]
            if not c.open_ or c.closed:
                continue
            if c.tref:  # holes given up ("end-of-capture"), a half-closed end
                self.ref_finish(ci, self.end_ts, "end-of-capture")
                continue
            if (c.h[0].fin >= 0 and not c.h[0].done) or (c.h[1].fin >= 0 and not c.h[1].done):
                raise Declined("a FIN not reached at the end (a gap)")
            if c.fin_by:
                self.event(self.end_ts, c.sid, EventKind.DISCONNECT,
                           {"how": "fin", "by": "client" if c.fin_by == 1 else "server",
                            "half_closed": True})
                self.close_stream(ci, self.end_ts)
                self.closed_conn(ci, self.end_ts)
        # the pipeline's finish: decoders flush (in the order they were made), every
        # pending request times out
        self.batch += 1
        if self.open_streams < 0:
            self.open_streams = len(self._sid_conn)
        when = self.pl_last
        for key in self.dec_order:
            self.flush_dir(key >> 1, key & 1, when)
        s = self.ahead
        while s >= 0:
            nxt = self.sp[s].anext
            while self.sp[s].count:
                e = self.sp[s].head
                self.timeout_record(self.due_by(e, when), e)
            s = nxt
        self.flush_out()



cdef bytes _inner(bytes obj):
    """A JSON object's text without its braces."""
    return obj[1:len(obj) - 1]


cdef object _plain(str text):
    """``text`` in UTF-8 when it can go into a JSON string as it is, else ``None``."""
    for ch in text:
        if ch in '"\\' or ord(ch) < 0x20:
            return None
    return text.encode("utf-8")


_RECORD_KIND = {}


def _init_kinds():
    from mbmon.model import Kind

    _RECORD_KIND[Kind.REQUEST] = RecordKind.REQUEST
    _RECORD_KIND[Kind.RESPONSE] = RecordKind.RESPONSE
    _RECORD_KIND[Kind.EXCEPTION] = RecordKind.EXCEPTION


_init_kinds()


# --------------------------------------------------------------------------- PDUs


cdef bint _ref_lines = False  # the frames being paired are Modbus/UDP's (udp_datagram)


cdef bint native_pdu(const uint8_t* d, int n, bint response, Native* req, Native* out):
    """Decode the PDUs whose line this module writes (``pdu._well_formed``'s cases,
    exceptions, answers whose request changes nothing or only trims bits); False
    for every other PDU, which the reference decoder and formatter take: also one
    longer than the spec's 253 bytes (MBAP length 255, marked malformed by the
    framing) and every PDU of a Modbus/UDP stream (its lines say "transport":"udp")."""
    cdef int fc, bc, address, count, value
    if n < 1 or n > 253 or _ref_lines:
        return False
    fc = d[0] & 0x7F
    out.fc = fc
    out.has_addr = 0
    out.address = 0
    out.count = -1
    out.nvalues = -1
    out.bits = 0
    out.vdata = NULL
    out.exc = -1
    out.onoff = 0
    if d[0] & 0x80:
        if not response or n != 2:
            return False
        out.kind = 2
        out.exc = d[1]
        return True
    if fc == 0 or fc > 0x10:
        return False
    out.kind = 1 if response else 0
    if response:
        if fc <= 4:
            if n < 3:
                return False
            bc = d[1]
            if n != bc + 2:
                return False
            out.vdata = d + 2
            if fc >= 3:
                if bc & 1:
                    return False
                if req != NULL and req.fc == fc and req.kind == 0 and bc != 2 * req.count:
                    return False  # decoded again with the request (a byte count it breaks)
                out.nvalues = bc >> 1
            else:
                out.bits = 1
                if req != NULL and req.fc == fc and req.kind == 0:
                    if bc != (req.count + 7) >> 3:
                        return False
                    out.nvalues = req.count  # the requested bits only
                else:
                    out.nvalues = 8 * bc
            return True
    else:
        if fc <= 4:
            if n != 5:
                return False
            address = (d[1] << 8) | d[2]
            count = (d[3] << 8) | d[4]
            if not 1 <= count <= (2000 if fc <= 2 else 125) or address + count > 0x10000:
                return False
            out.has_addr = 1
            out.address = address
            out.count = count
            return True
        if fc >= 0x0F and n != 5:
            if n < 6:
                return False
            bc = d[5]
            count = (d[3] << 8) | d[4]
            address = (d[1] << 8) | d[2]
            if n - 6 != bc or count < 1 or address + count > 0x10000:
                return False
            out.has_addr = 1
            out.address = address
            out.count = count
            out.vdata = d + 6
            out.nvalues = count
            if fc == 0x0F:
                if count > 1968 or bc != (count + 7) >> 3:
                    return False
                out.bits = 1
            else:
                if count > 123 or bc != 2 * count:
                    return False
            return True
    if n != 5:
        return False
    address = (d[1] << 8) | d[2]
    value = (d[3] << 8) | d[4]
    out.has_addr = 1
    out.address = address
    if fc == 5:
        if value != 0xFF00 and value != 0:
            return False
        out.count = 1
        out.nvalues = 1
        out.bits = 1
        out.onoff = 1
        out.vdata = d + 3  # 0xFF: ON, 0x00: OFF (read as the first bit)
        return True
    if fc == 6:
        out.count = 1
        out.nvalues = 1
        out.vdata = d + 3
        return True
    if fc >= 0x0F and response:
        if not 1 <= value <= (1968 if fc == 0x0F else 123) or address + value > 0x10000:
            return False
        out.count = value
        return True
    return False


cdef int put_values_json(Buf* o, Native* n) except -1:
    cdef int i
    if n.nvalues < 0:
        return put(o, b"null", 4)
    put_c(o, 91)
    for i in range(n.nvalues):
        if i:
            put_c(o, 44)
        if n.onoff:
            put_c(o, 49 if n.vdata[0] else 48)
        elif n.bits:
            put_c(o, 49 if (n.vdata[i >> 3] >> (i & 7)) & 1 else 48)
        else:
            put_u16(o, be16(n.vdata + 2 * i))
    return put_c(o, 93)


def _native_note(bytes data, bint response, request=None):
    """Test-only entry: ``None`` when the core leaves the PDU to the reference decoder,
    else ``(fc, kind, address, count, values, note)`` as the core writes them (a
    response with ``request``: as paired with that request's PDU)."""
    cdef Native nat, rnat
    cdef Native* rp = NULL
    cdef bytes req = request
    cdef bint ok
    cdef _Pass p
    if req is not None:
        if not native_pdu(<const uint8_t*><char*>req, len(req), False, NULL, &rnat):
            return None
        rp = &rnat
    ok = native_pdu(<const uint8_t*><char*>data, len(data), response, rp, &nat)
    if not ok:
        return None
    p = _Pass(True, False, 1.0, frozenset(), None, None)
    if p.fnames[nat.fc] is None or (nat.exc >= 0 and p.enames[nat.exc] is None):
        return None
    if rp != NULL and nat.kind != 0 and not nat.has_addr and rnat.has_addr:
        nat.has_addr = 1
        nat.address = rnat.address
        nat.count = rnat.count
    p.put_note(&nat)
    note = PyBytes_FromStringAndSize(p.out.p, p.out.n).decode("utf-8")
    p.out.n = 0
    put_values_json(&p.out, &nat)
    values = _orjson.loads(PyBytes_FromStringAndSize(p.out.p, p.out.n))
    return (
        nat.fc,
        ("request", "response", "exception")[nat.kind],
        nat.address if nat.has_addr else None,
        nat.count if nat.has_addr and nat.count >= 0 else None,
        values,
        nat.exc if nat.exc >= 0 else None,
        note,
    )


def _fixed_text(double v, int precision):
    """Test-only entry: ``fixed_text``'s ``'%.Nf' % v`` (bytes), or ``None`` where it
    proves nothing (the core asks CPython there)."""
    cdef char tmp[24]
    cdef int n = fixed_text(tmp, v, precision)
    return None if n < 0 else PyBytes_FromStringAndSize(tmp, n)


def _round3(double v):
    """Test-only entry: ``round3_exact(v)`` (NaN where it proves nothing)."""
    return round3_exact(v)


def _boxed(list pieces, Py_ssize_t room):
    """Test-only entry: ``pieces`` written one after the other into a boxed ``Buf`` of
    ``room`` bytes (grown as a log block is: ``box_grow``), and the bytes object it was
    written in, as :func:`box_take` hands it over (its address: the second member)."""
    cdef Buf b
    b.p = NULL
    b.n = 0
    b.cap = 0
    b.box = NULL
    cdef size_t at
    try:
        box_new(&b, room)
        for piece in pieces:
            put_bytes(&b, piece)
        at = <size_t>b.p
        return box_take(&b), at
    finally:
        buf_free(&b)


def _json_round3(double v):
    """Test-only entry: the JSON number a line's ``latency_ms`` gets (``put_json_round3``)."""
    cdef Buf b
    b.p = NULL
    b.n = 0
    b.cap = 0
    b.box = NULL
    try:
        put_json_round3(&b, v)
        return PyBytes_FromStringAndSize(b.p, b.n)
    finally:
        free(b.p)


cdef bint _same_as_cpython(double x, char* mine, int* unproven) except -1:
    """Whether ``fixed_text`` and ``round3_exact`` give what CPython gives for ``x``
    (``'%.1f'``, ``'%.3f'`` and ``round(x, 3)`` read back, bit for bit)."""
    cdef int prec, n
    cdef char* s
    cdef double r = 0.0, mr
    cdef bint same = True
    for prec in (1, 3):
        n = fixed_text(mine, x, prec)
        if n < 0:
            unproven[0] += 1
            return True
        s = PyOS_double_to_string(x, b'f', prec, 0, NULL)
        try:
            if <size_t>n != strlen(s) or memcmp(s, mine, n) != 0:
                same = False
            if prec == 3:
                r = PyOS_string_to_double(s, NULL, None)
        finally:
            PyMem_Free(s)
    mr = round3_exact(x)
    if memcmp(&r, &mr, 8) != 0:
        same = False
    return same


def _latency_sweep(int64_t sec, int64_t frac0, int64_t divisor, int64_t count,
                   int64_t step=1, bint pcapng=False, bint negative=True):
    """Test-only entry: every latency ``ts(k) - ts(0)`` in ms, for the capture times
    ``sec + (frac0 + k * step) / divisor`` (k < ``count``) as the pcap reader makes
    them (``sec + frac / divisor``; ``pcapng``: one stamp ``/ divisor``), and with
    ``negative`` the other way round too (a response before its request), checked
    against CPython's own formatting: ``(checked, mismatches, first mismatching
    latency or None, unproven)``."""
    cdef int64_t k, t, bad = 0, checked = 0
    cdef int unproven = 0, j
    cdef double t0, tk, x
    cdef double dv = <double>divisor
    cdef char mine[24]
    first = None
    if pcapng:
        t0 = <double>(sec * divisor + frac0) / dv
    else:
        t0 = <double>sec + <double>frac0 / dv
    for k in range(count):
        t = frac0 + k * step
        if pcapng:
            tk = <double>(sec * divisor + t) / dv
        else:
            tk = <double>(sec + t // divisor) + <double>(t % divisor) / dv
        for j in range(2 if negative else 1):
            x = (tk - t0) * 1000 if j == 0 else (t0 - tk) * 1000
            checked += 1
            if not _same_as_cpython(x, mine, &unproven):
                bad += 1
                if first is None:
                    first = x
    return checked, bad, first, unproven

include "_live.pxi"
include "_rtu_pass.pxi"
include "_chunks.pxi"


def _slim_frame_json(bytes data, Py_ssize_t start, Py_ssize_t end):
    """Test-only entry: ``layout.slim_frame_json(data, start, end)`` as the core makes a
    frame's format-2 message in place (``slim_frame``)."""
    if not (8 <= start < end <= len(data)):
        raise ValueError("the line string must lie inside the data")
    cdef bytearray b = bytearray(data)
    cdef char* p = b
    cdef Py_ssize_t n = slim_frame(p, len(b), start - 8, end)
    return bytes(b[:n])
