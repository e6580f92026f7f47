"""What every stream decoder shares: its buffer and the current run of noise bytes.

Bytes a decoder cannot frame are collected into one run, reported as a single
:class:`~mbmon.model.Noise` with the reason the run began for, when the next
frame is found, at a gap (``reset``) or at the end of the stream.
"""

from __future__ import annotations

from mbmon.model import Direction, Noise, Stream


class StreamDecoder:
    """Base of the MBAP and RTU decoders: one stream direction (or a bus), sans-I/O."""

    __slots__ = ("_buf", "_noise", "_noise_reason", "_noise_ts", "direction", "stream")

    def __init__(self, stream: Stream, direction: Direction) -> None:
        self.stream = stream
        self.direction = direction
        self._buf = bytearray()
        self._noise = bytearray()
        self._noise_reason = ""
        self._noise_ts = 0.0

    def _take_noise(self) -> Noise | None:
        """End the current noise run and return it (``None`` when there is none)."""
        return self._flush_noise_run() if self._noise else None

    def _flush_noise_run(self) -> Noise:
        run = Noise(
            self._noise_ts, self.stream, self.direction, bytes(self._noise), self._noise_reason
        )
        self._noise = bytearray()
        return run

    def _discard(self, ts: float) -> list[Noise]:
        """The noise run and the unframed buffer, dropped (a gap): what ``reset`` reports."""
        out: list[Noise] = []
        run = self._take_noise()
        if run is not None:
            out.append(run)
        if self._buf:
            out.append(
                Noise(ts, self.stream, self.direction, bytes(self._buf), "discarded after gap")
            )
            self._buf = bytearray()
        return out
