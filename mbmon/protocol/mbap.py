"""MBAP (Modbus/TCP and Modbus/UDP) stream decoder: bytes of one direction -> frames.

An MBAP ADU is a 7-byte header (transaction id, protocol id 0, length, unit id)
followed by the PDU; ``length`` counts the unit id and the PDU. Framing loops
over the length field, so several ADUs in one segment and one ADU split over
several segments (even inside its header) decode identically (DESIGN rule 4).

Bytes that cannot be an MBAP header (protocol id != 0, length outside
2..255) start a run of noise. The decoder then resynchronises on the next
corroborated header: protocol id 0, length in range, a plausible function
code (requests 0x01..0x7F, responses 0x01..0x7F or 0x81..0xFF) and either a
predictable PDU length that the length field agrees with (up to
``TRAILING_SLACK`` trailing bytes allowed) or, for codes of unpredictable
length, another header right after it or the end of the stream right after
it (see :meth:`MbapDecoder._corroborated`). Length 255, one over the spec, is
decoded and marked malformed (:data:`TOLERATED_LENGTH`). Outside a noise
run any function code is accepted (a sweep of every code starts with 0x00), so
the first bytes of a stream, or the first after :meth:`MbapDecoder.reset`, are
taken as a header when protocol id and length allow it; a capture that starts
in the middle of an ADU falls into a noise run and resynchronises. One :class:`Noise`
is reported per run of skipped bytes (split only every ``NOISE_CAP`` bytes so
that memory stays bounded), stamped when its first byte arrived, just before
the frame that ends the run, or at ``flush``/``reset``/``tick``; undecided
bytes at the end of the stream join the run they continue.

Pure: no I/O, no clocks; time is the ``ts`` given with each chunk.
"""

from __future__ import annotations

from mbmon.model import Direction, Frame, Noise, Stream, fast_constructor
from mbmon.protocol.pdu import NEED_MORE, decode_pdu, pdu_length, with_malformed
from mbmon.protocol.stream import StreamDecoder

__all__ = [
    "DEFAULT_MAX_LENGTH",
    "MBAP_HEADER_LEN",
    "NOISE_CAP",
    "TOLERATED_LENGTH",
    "MbapDecoder",
    "encode_adu",
    "length_note",
]

MBAP_HEADER_LEN = 7
"""Transaction id (2), protocol id (2), length (2), unit id (1)."""

DEFAULT_MAX_LENGTH = 254
"""Largest MBAP length field of a clean ADU: unit id + a 253-byte PDU (spec limit)."""

TOLERATED_LENGTH = 255
"""One over the spec: real PLCs send it (Schneider UMAS, function code 0x5A) and
tshark decodes it. With the default ``max_length`` an ADU with length 255 is
decoded, its PDU marked ``malformed`` ("MBAP length 255 exceeds 254"); 256 and
more stay noise (tshark takes any length, but a longer field is far more often
noise than an ADU, and taking it would swallow the ADUs after it)."""

TRAILING_SLACK = 4
"""Trailing bytes after a PDU of predictable length still accepted when resynchronising."""

_NO_HEADER = "no plausible MBAP header"

NOISE_CAP = 65536
"""A noise run longer than this is reported in pieces of this size."""

_new_frame = fast_constructor(Frame)  # one per ADU: about twice as fast as Frame(...)

# Modes of one decoding pass.
_STREAM = 0  # more bytes will come: wait whenever a decision needs them
_SETTLE = 1  # a silence follows (tick): a resync candidate ending the bytes is corroborated
_FINAL = 2  # end of stream: decide everything with the bytes present


def length_note(raw: bytes | bytearray) -> str | None:
    """The spec breach of an MBAP ADU's length field, or ``None`` (``raw`` = whole ADU)."""
    length = len(raw) - 6
    if length > DEFAULT_MAX_LENGTH:
        return f"MBAP length {length} exceeds {DEFAULT_MAX_LENGTH}"
    return None


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
    (responses). ``max_length`` is the largest MBAP length field of a clean ADU
    (default 254, the spec limit); with the default, length 255 is decoded too
    and marked malformed (:data:`TOLERATED_LENGTH`). ``silence`` (seconds, or
    ``None``) is how long the stream must be quiet before :meth:`tick` reports
    the current noise run and takes a resync candidate that ends the bytes
    received. The decoder owns its buffer, the current noise run and the sync
    state; it never raises on input bytes.
    """

    __slots__ = (
        "_limit",
        "_max_length",
        "_response",
        "_silence",
        "_synced",
        "_ticked",
    )

    def __init__(
        self,
        stream: Stream,
        direction: Direction,
        max_length: int = DEFAULT_MAX_LENGTH,
        silence: float | None = None,
    ) -> None:
        if direction is Direction.BUS:
            raise ValueError("an MBAP stream direction must be C2S or S2C")
        super().__init__(stream, direction)
        self._response = direction is Direction.S2C
        # _max_length: clean ADUs (the fused reader frames only these);
        # _limit: what the decoder takes, one over the spec with the default
        self._max_length = max(2, min(int(max_length), DEFAULT_MAX_LENGTH))
        self._limit = TOLERATED_LENGTH if max_length >= DEFAULT_MAX_LENGTH else self._max_length
        self._synced = True
        self._silence = silence
        self._ticked: float | None = None  # the _last_ts a tick settled

    @property
    def synced(self) -> bool:
        """Whether the decoder is framing on the length field (not inside a noise run)."""
        return self._synced

    # ------------------------------------------------------------------ public

    def feed(self, data: bytes, ts: float) -> list[Frame | Noise]:
        """Consume one chunk captured at ``ts``; return the frames and noise it completes."""
        self._last_ts = ts
        old = len(self._buf)
        if not old and self._synced and not self._noise:
            # one whole clean ADU and nothing held: what _decode gives, without its loop
            # (a proxy's segments, most live ones). split_clean's one-ADU case, inlined:
            # calling it here cost 0.3-0.4 us per ADU (a call, two lists)
            n = len(data)
            if (
                8 <= n <= 6 + self._max_length
                and data[2] == 0
                and data[3] == 0
                and ((data[4] << 8) | data[5]) == n - 6
            ):
                raw = data if type(data) is bytes else bytes(data)
                return [
                    _new_frame(
                        ts,
                        self.stream,
                        self.direction,
                        raw[6],
                        (raw[0] << 8) | raw[1],
                        decode_pdu(raw[7:], self._response),
                        raw,
                        None,
                    )
                ]
        out: list[Frame | Noise] = []
        if old:
            self._buf += data
            buf: bytes | bytearray = self._buf
        else:
            buf = data  # fast path: decode straight from the chunk, no copy
        pos = self._decode(buf, ts, out, old, _STREAM)
        self._keep(buf, pos, old, ts)
        return out

    def split_clean(self, data: bytes, ts: float) -> list[bytes] | None:
        """The ADUs of ``data`` as bytes, without decoding their PDUs, when nothing
        is buffered and ``data`` is whole clean ADUs (protocol id 0, length within
        ``max_length``) ending exactly at its end; ``None`` otherwise, and the
        decoder is untouched: :meth:`feed` then decides (it would give frames with
        these very bytes). The proxy's fast path: it forwards ADUs, the hub decodes."""
        if self._buf or self._noise or not self._synced:
            return None
        n = len(data)
        if n >= 8 and data[2] == 0 and data[3] == 0:
            end = 6 + ((data[4] << 8) | data[5])
            if end == n:  # one ADU: by far the most common segment
                if n <= 6 + self._max_length:
                    self._last_ts = ts
                    return [data]
                return None
        out: list[bytes] = []
        pos = 0
        max_end = 6 + self._max_length
        while pos < n:
            if n - pos < 8 or data[pos + 2] != 0 or data[pos + 3] != 0:
                return None
            length = (data[pos + 4] << 8) | data[pos + 5]
            if length < 2 or length + 6 > max_end or pos + 6 + length > n:
                return None
            out.append(data[pos : pos + 6 + length])
            pos += 6 + length
        if not out:
            return None
        self._last_ts = ts
        return out

    def feed_adus(self, data: bytes, ts: float) -> tuple[list[bytes], Noise | None]:
        """:meth:`feed` for a forwarder: the bytes of the ADUs ``data`` completes, up to
        the first noise, and that noise (``None`` if there is none); what the proxy
        does with a read that :meth:`split_clean` declined (a split ADU, garbage)."""
        raws: list[bytes] = []
        for item in self.feed(data, ts):
            if not isinstance(item, Frame):
                return raws, item
            raws.append(item.raw)
        return raws, None

    def flush(self, ts: float) -> list[Frame | Noise]:
        """End of stream: a resync candidate is judged with the bytes present, and
        the noise run with every undecided byte becomes one :class:`Noise`."""
        out: list[Frame | Noise] = []
        if self._buf:
            old = len(self._buf)
            last = self._last_ts if self._last_ts is not None else ts
            pos = self._decode(self._buf, last, out, old, _FINAL)
            del self._buf[:pos]
        out.extend(self._settle_rest("truncated ADU at end of stream"))
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

    def tick(self, now: float) -> list[Frame | Noise]:
        """After ``silence`` without bytes: a resync candidate that ends the bytes
        received is taken (the end of a quiet sender's message corroborates it)
        and the noise run so far is reported. A partial ADU keeps waiting."""
        deadline = self.next_deadline()
        if deadline is None or now < deadline:
            return []
        self._ticked = self._last_ts
        out: list[Frame | Noise] = []
        if self._buf and not self._synced:
            old = len(self._buf)
            pos = self._decode(self._buf, self._last_ts or now, out, old, _SETTLE)
            del self._buf[:pos]
        run = self._take_noise()
        if run is not None:
            out.append(run)
        return out

    def next_deadline(self) -> float | None:
        """When :meth:`tick` would settle a noise run or resync candidate, or ``None``."""
        last = self._last_ts
        if (
            self._silence is None
            or last is None
            or self._ticked == last
            or not (self._noise or (self._buf and not self._synced))
        ):
            return None
        return last + self._silence

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

    def _decode(
        self, buf: bytes | bytearray, ts: float, out: list[Frame | Noise], old: int, mode: int
    ) -> int:
        """Frame ADUs from ``buf``; return the offset of the first undecided byte.

        ``buf[:old]`` arrived at ``_buf_ts``, the rest at ``ts`` (noise is
        stamped when its bytes arrived; frames when their last byte did).
        """
        n = len(buf)
        pos = 0
        max_len = self._max_length
        limit = self._limit
        response = self._response
        stream = self.stream
        direction = self.direction
        append = out.append
        copy = type(buf) is not bytes  # a slice of bytes is bytes already
        while n - pos >= 6:
            if buf[pos + 2] == 0 and buf[pos + 3] == 0:
                length = (buf[pos + 4] << 8) | buf[pos + 5]
                if 2 <= length <= limit:
                    end = pos + 6 + length
                    if self._synced:
                        if end > n:
                            break
                    elif n - pos < 8:
                        break  # a resync candidate is judged by its function code
                    else:
                        verdict = self._corroborated(buf, pos, end, n, length, mode)
                        if verdict < 0:
                            break
                        if verdict == 0:
                            nxt = self._next_candidate(buf, pos)
                            arrived = self._buf_ts if pos < old else ts
                            self._add_noise(buf[pos:nxt], _NO_HEADER, arrived, out)
                            pos = nxt
                            continue
                        if end > n:
                            break
                        self._synced = True
                    if self._noise:
                        append(self._flush_noise_run())
                    raw = bytes(buf[pos:end]) if copy else buf[pos:end]
                    pdu = decode_pdu(raw[7:], response)
                    if length > max_len:
                        pdu = with_malformed(pdu, f"MBAP length {length} exceeds {max_len}")
                    append(
                        _new_frame(
                            # a resync candidate judged later keeps its own bytes' time
                            ts if end > old else self._buf_ts,
                            stream,
                            direction,
                            raw[6],
                            (raw[0] << 8) | raw[1],
                            pdu,
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
            self._add_noise(buf[pos:nxt], reason, self._buf_ts if pos < old else ts, out)
            pos = nxt
        return pos

    def _corroborated(
        self, buf: bytes | bytearray, pos: int, end: int, n: int, length: int, mode: int
    ) -> int:
        """Whether the resync candidate at ``pos`` becomes an ADU: 1 yes, 0 no, -1 wait.

        A header found after noise needs corroboration:

        * its function code must be valid for the direction, and
        * when the code has a predictable PDU length (told by the bytes present),
          the length field must agree with it, give or take up to
          ``TRAILING_SLACK`` trailing bytes (some devices pad);
        * when it has none (unknown and user-defined codes, 0x2B, ...), the
          bytes right after it must start another header (protocol id 0, length
          in range), or the candidate must end the bytes exactly at the end of
          the stream (``flush``: also the end of each UDP datagram) or before a
          silence (``tick``). The end of a TCP segment is *not* taken: it would
          make the frames depend on how the stream was cut into chunks.

        Undecidable yet (bytes missing) is -1: the caller waits for more.
        """
        fc = buf[pos + 7]
        response = self._response
        if fc == 0 or fc == 0x80 or (fc & 0x80 and not response):
            return 0
        plen = pdu_length(buf[pos + 7 : min(end, n)], response)
        if plen is not None:
            if plen == NEED_MORE:
                return -1 if end > n else 0
            return 1 if 0 < plen <= length - 1 <= plen + TRAILING_SLACK else 0
        if end > n:
            return -1
        if n - end >= 6:
            nxt_len = (buf[end + 4] << 8) | buf[end + 5]
            lined_up = buf[end + 2] == 0 and buf[end + 3] == 0 and 2 <= nxt_len <= self._limit
            return 1 if lined_up else 0
        if end == n and mode != _STREAM:
            return 1
        return 0 if mode == _FINAL else -1

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
