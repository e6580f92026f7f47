"""What every stream decoder shares: its buffer and the current run of noise bytes.

Bytes a decoder cannot frame are collected into one run, reported as a single
:class:`~mbmon.model.Noise` with the reason the run began for, when the next
frame is found, at a gap (``reset``), at a silence (``tick``) or at the end of
the stream. A run is stamped with the capture time of its first byte: bytes
that wait in the buffer keep the time they arrived (``_buf_ts``), so undecided
bytes settled at the end of a stream join the run they continue instead of
becoming a second record stamped at the end.
"""

from __future__ import annotations

from mbmon.model import Direction, Frame, Noise, Stream


class StreamDecoder:
    """Base of the MBAP and RTU decoders: one stream direction (or a bus), sans-I/O.

    ``_buf_ts`` is the capture time of the chunk that brought the first byte
    still in ``_buf`` (an approximation when the buffer spans several chunks:
    the earliest of them). ``_last_ts`` is the time of the last chunk fed.
    """

    __slots__ = (
        "_buf",
        "_buf_ts",
        "_last_ts",
        "_noise",
        "_noise_reason",
        "_noise_ts",
        "direction",
        "stream",
    )

    def __init__(self, stream: Stream, direction: Direction) -> None:
        self.stream = stream
        self.direction = direction
        self._buf = bytearray()
        self._buf_ts = 0.0
        self._last_ts: float | None = None
        self._noise = bytearray()
        self._noise_reason = ""
        self._noise_ts = 0.0

    @property
    def buffered(self) -> int:
        """Bytes held: undecided bytes plus the noise run not yet reported."""
        return len(self._buf) + len(self._noise)

    def tick(self, now: float) -> list[Frame | Noise]:
        """Time moved on to ``now`` without bytes; the base decoder has nothing to settle."""
        return []

    def next_deadline(self) -> float | None:
        """When :meth:`tick` would settle something, or ``None`` (nothing waits on time)."""
        return None

    def _take_noise(self) -> Noise | None:
        """End the current noise run and return it (``None`` when there is none)."""
        return self._flush_noise_run() if self._noise else None

    def _flush_noise_run(self) -> Noise:
        run = Noise(
            self._noise_ts, self.stream, self.direction, bytes(self._noise), self._noise_reason
        )
        self._noise = bytearray()
        return run

    def _keep(self, buf: bytes | bytearray, pos: int, old: int, ts: float) -> None:
        """Keep ``buf[pos:]`` undecided after a decoding pass over ``buf``.

        ``old`` is how many bytes of ``buf`` were buffered before this chunk
        (``buf`` is ``_buf`` then); their arrival time is ``_buf_ts``, the
        chunk's is ``ts``.
        """
        if buf is self._buf:
            del self._buf[:pos]  # O(1) in CPython: moves the start pointer
            if pos >= old:
                self._buf_ts = ts
        elif pos < len(buf):
            self._buf = bytearray(buf[pos:])
            self._buf_ts = ts

    def _settle_rest(self, reason: str) -> list[Noise]:
        """The undecided buffer, dropped: it joins the noise run (one record), or
        becomes a run of its own with ``reason`` stamped when its bytes arrived."""
        out: list[Noise] = []
        if self._buf:
            if not self._noise:
                self._noise_reason = reason
                self._noise_ts = self._buf_ts
            self._noise += self._buf
            self._buf = bytearray()
        run = self._take_noise()
        if run is not None:
            out.append(run)
        return out

    def _discard(self, ts: float) -> list[Noise]:
        """The noise run and the unframed buffer, dropped (a gap): what ``reset`` reports."""
        return self._settle_rest("discarded after gap")
