"""MBAP (Modbus/TCP and Modbus/UDP) stream decoder: bytes of one direction -> frames.

An MBAP ADU is a 7-byte header (transaction id, protocol id 0, length, unit id)
followed by the PDU; ``length`` counts the unit id and the PDU. Framing loops
over the length field, so several ADUs in one segment and one ADU split over
several segments (even inside its header) decode identically (DESIGN rule 4).

Bytes that cannot be an MBAP header (protocol id != 0, length outside
2..``max_length``) start a run of noise. The decoder then resynchronises on the
next plausible header: protocol id 0, length in range, a plausible function
code (requests 0x01..0x7F, responses 0x01..0x7F or 0x81..0xFF) and, when the
function code has a predictable PDU length, a length field that agrees with it
(up to ``TRAILING_SLACK`` trailing bytes allowed). Outside a noise
run any function code is accepted (a sweep of every code starts with 0x00), so
the first bytes of a stream, or the first after :meth:`MbapDecoder.reset`, are
taken as a header when protocol id and length allow it; a capture that starts
in the middle of an ADU falls into a noise run and resynchronises. One :class:`Noise`
is reported per run of skipped bytes (split only every ``NOISE_CAP`` bytes so
that memory stays bounded), just before the frame that ends the run, or at
``flush``/``reset``.

Pure: no I/O, no clocks; time is the ``ts`` given with each chunk.
"""

from __future__ import annotations

from mbmon.model import Direction, Frame, Noise, Stream, fast_constructor
from mbmon.protocol.pdu import NEED_MORE, decode_pdu, pdu_length
from mbmon.protocol.stream import StreamDecoder

__all__ = ["DEFAULT_MAX_LENGTH", "MBAP_HEADER_LEN", "NOISE_CAP", "MbapDecoder", "encode_adu"]

MBAP_HEADER_LEN = 7
"""Transaction id (2), protocol id (2), length (2), unit id (1)."""

DEFAULT_MAX_LENGTH = 254
"""Largest MBAP length field accepted: unit id + a 253-byte PDU (spec limit)."""

TRAILING_SLACK = 4
"""Trailing bytes after a PDU of predictable length still accepted when resynchronising."""

_NO_HEADER = "no plausible MBAP header"

NOISE_CAP = 65536
"""A noise run longer than this is reported in pieces of this size."""

_new_frame = fast_constructor(Frame)  # one per ADU: about twice as fast as Frame(...)


def encode_adu(tid: int, unit: int, pdu: bytes) -> bytes:
    """MBAP ADU for ``pdu``: header with protocol id 0 and length = 1 + len(pdu)."""
    if not 0 <= tid <= 0xFFFF:
        raise ValueError(f"transaction id {tid} does not fit in 16 bits")
    if not 0 <= unit <= 0xFF:
        raise ValueError(f"unit id {unit} does not fit in a byte")
    length = len(pdu) + 1
    if length > 0xFFFF:
        raise ValueError(f"PDU of {len(pdu)} bytes is too long for MBAP")
    return bytes((tid >> 8, tid & 0xFF, 0, 0, length >> 8, length & 0xFF, unit)) + bytes(pdu)


class MbapDecoder(StreamDecoder):
    """Sans-I/O decoder of one TCP/UDP direction carrying MBAP ADUs.

    ``direction`` is C2S (requests, decoded with ``response=False``) or S2C
    (responses). ``max_length`` is the largest MBAP length field taken as a
    header (default 254, the spec limit). The decoder owns its buffer, the
    current noise run and the sync state; it never raises on input bytes.
    """

    __slots__ = (
        "_max_length",
        "_response",
        "_synced",
    )

    def __init__(
        self, stream: Stream, direction: Direction, max_length: int = DEFAULT_MAX_LENGTH
    ) -> None:
        if direction is Direction.BUS:
            raise ValueError("an MBAP stream direction must be C2S or S2C")
        super().__init__(stream, direction)
        self._response = direction is Direction.S2C
        self._max_length = max(2, min(int(max_length), 0xFFFF))
        self._synced = True

    # ------------------------------------------------------------------ public

    @property
    def synced(self) -> bool:
        """False while the decoder skips bytes that are not MBAP (a noise run is open)."""
        return self._synced

    def feed(self, data: bytes, ts: float) -> list[Frame | Noise]:
        """Consume one chunk captured at ``ts``; return the frames and noise it completes."""
        out: list[Frame | Noise] = []
        if self._buf:
            self._buf += data
            buf: bytes | bytearray = self._buf
        else:
            buf = data  # fast path: decode straight from the chunk, no copy
        pos = self._decode(buf, ts, out)
        if buf is self._buf:
            del self._buf[:pos]  # O(1) in CPython: moves the start pointer
        elif pos < len(buf):
            self._buf = bytearray(buf[pos:])
        return out

    def flush(self, ts: float) -> list[Frame | Noise]:
        """End of stream: the noise run and any incomplete ADU become :class:`Noise`."""
        out: list[Frame | Noise] = []
        run = self._take_noise()
        if run is not None:
            out.append(run)
        if self._buf:
            out.append(
                Noise(
                    ts,
                    self.stream,
                    self.direction,
                    bytes(self._buf),
                    "truncated ADU at end of stream",
                )
            )
            self._buf = bytearray()
        self._synced = True
        return out

    def reset(self, ts: float) -> list[Noise]:
        """Drop the buffer (e.g. after a TCP gap); report what was dropped as noise.

        The next bytes are taken as the start of an ADU (a TCP segment after a
        gap usually starts one); if they are not, the decoder resynchronises.
        """
        out = self._discard(ts)
        self._synced = True
        return out

    # ------------------------------------------------------------------ internals

    def _add_noise(
        self, chunk: bytes | bytearray, reason: str, ts: float, out: list[Frame | Noise]
    ) -> None:
        if not self._noise:
            self._noise_reason = reason
            self._noise_ts = ts
        self._noise += chunk
        while len(self._noise) >= NOISE_CAP:
            piece = bytes(self._noise[:NOISE_CAP])
            del self._noise[:NOISE_CAP]
            out.append(
                Noise(self._noise_ts, self.stream, self.direction, piece, self._noise_reason)
            )
            self._noise_ts = ts

    def _decode(self, buf: bytes | bytearray, ts: float, out: list[Frame | Noise]) -> int:
        """Frame ADUs from ``buf``; return the offset of the first undecided byte."""
        n = len(buf)
        pos = 0
        max_len = self._max_length
        response = self._response
        stream = self.stream
        direction = self.direction
        append = out.append
        copy = type(buf) is not bytes  # a slice of bytes is bytes already
        while n - pos >= 6:
            if buf[pos + 2] == 0 and buf[pos + 3] == 0:
                length = (buf[pos + 4] << 8) | buf[pos + 5]
                if 2 <= length <= max_len:
                    end = pos + 6 + length
                    if self._synced:
                        if end > n:
                            break
                    elif n - pos < 8:
                        break  # a resync candidate is judged by its function code
                    elif not self._plausible(buf, pos, min(end, n), length):
                        nxt = self._next_candidate(buf, pos)
                        self._add_noise(buf[pos:nxt], _NO_HEADER, ts, out)
                        pos = nxt
                        continue
                    elif end > n:
                        break
                    else:
                        self._synced = True
                    if self._noise:
                        append(self._flush_noise_run())
                    raw = bytes(buf[pos:end]) if copy else buf[pos:end]
                    append(
                        _new_frame(
                            ts,
                            stream,
                            direction,
                            raw[6],
                            (raw[0] << 8) | raw[1],
                            decode_pdu(raw[7:], response),
                            raw,
                            None,
                        )
                    )
                    pos = end
                    continue
                else:
                    reason = f"bad MBAP length {length}"
            else:
                proto = (buf[pos + 2] << 8) | buf[pos + 3]
                reason = f"bad MBAP header (protocol id 0x{proto:04X})"
            self._synced = False
            nxt = self._next_candidate(buf, pos)
            self._add_noise(buf[pos:nxt], reason, ts, out)
            pos = nxt
        return pos

    def _plausible(self, buf: bytes | bytearray, pos: int, end: int, length: int) -> bool:
        """Whether the resync candidate at ``pos`` (bytes present up to ``end``) may be an ADU.

        Its function code must be valid for the direction, and when the code has
        a predictable PDU length (told by the bytes present) the length field
        must agree with it, give or take up to ``TRAILING_SLACK`` trailing bytes
        (some devices send a few). A candidate that cannot be judged yet is
        plausible for now: the caller waits for the rest of the ADU.
        """
        fc = buf[pos + 7]
        response = self._response
        if fc == 0 or fc == 0x80 or (fc & 0x80 and not response):
            return False
        plen = pdu_length(buf[pos + 7 : end], response)
        if plen is None:
            return True
        if plen == NEED_MORE:
            return end - pos < 6 + length
        return 0 < plen <= length - 1 <= plen + TRAILING_SLACK

    @staticmethod
    def _next_candidate(buf: bytes | bytearray, pos: int) -> int:
        """Offset of the next position after ``pos`` that may start a header.

        A header needs protocol id 0: the next ``00 00`` pair at offset >= pos+3
        marks a candidate two bytes before it. Without one, the last three bytes
        stay undecided (their protocol id is not complete yet).
        """
        idx = buf.find(b"\x00\x00", pos + 3)
        if idx >= 0:
            return idx - 2
        return max(pos + 1, len(buf) - 3)
