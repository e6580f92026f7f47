"""The bytes of one frame typed by hand (``mbmon decode``) as a source of the hub.

:class:`TypedFrameSource` implements the source contract (:mod:`mbmon.sources.base`):
its one chunk goes through the same pairing and annotation as a capture's, so the
frame is annotated and written by the same code (``format.py``'s lines and JSON
record); ``decode`` prints the records this source gives, and nothing else.

The framing is the caller's to decide (``rtu``: unit, PDU, CRC; ``tcp``: an MBAP
header; ``pdu``: a bare PDU, unit ``unit``, no transaction id), and the bytes are
one ADU exactly: the stream is framed by :class:`TypedAduDecoder` (one chunk, one
frame: an RTU frame whose CRC fails is that frame with its CRC verdict, not noise
as on a bus; an MBAP length field that disagrees is the caller's to warn about),
which the source names for its stream (:meth:`~mbmon.pipeline.Pipeline.use_decoder`).
The bytes are a request unless ``response`` (or the function code's exception bit)
says otherwise. The stream is untimed: no time or latency is shown, and a request
typed alone is never reported unanswered (nothing after it was observed).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Literal

from mbmon.model import Chunk, Direction, Frame, Noise, Stream, Transport
from mbmon.protocol.crc import check_crc
from mbmon.protocol.pdu import decode_pdu
from mbmon.sources.base import BaseSource, SourceMode

if TYPE_CHECKING:
    from mbmon.hub import Hub, Item
    from mbmon.pipeline import PipelineConfig, StreamDecoding

__all__ = ["Framing", "TypedAduDecoder", "TypedFrameError", "TypedFrameSource", "adu_parts"]

Framing = Literal["rtu", "tcp", "pdu"]


class TypedFrameError(ValueError):
    """Too few bytes for the framing asked (the message says what it needs)."""


def adu_parts(data: bytes, framing: Framing, unit: int = 0) -> tuple[int, int | None, bytes]:
    """``(unit, transaction id, PDU)`` of one ADU in ``framing``; :class:`TypedFrameError`
    when the bytes are too few for it."""
    if framing == "rtu":
        if len(data) < 4:
            raise TypedFrameError("an RTU ADU needs at least 4 bytes (unit, function code, CRC)")
        return data[0], None, data[1:-2]
    if framing == "tcp":
        if len(data) < 8:
            raise TypedFrameError(
                "a Modbus/TCP ADU needs at least 8 bytes (7-byte MBAP header + fc)"
            )
        return data[6], int.from_bytes(data[0:2]), data[7:]
    return unit, None, data


class TypedAduDecoder:
    """The stream decoder of typed bytes: each chunk is one whole ADU in ``framing``
    (sans-I/O, nothing buffered)."""

    buffered = 0

    def __init__(self, stream: Stream, direction: Direction, framing: Framing, unit: int) -> None:
        self.stream = stream
        self.direction = direction
        self.framing = framing
        self.unit = unit

    def feed(self, data: bytes, ts: float) -> list[Frame | Noise]:
        """The one frame of ``data`` (its CRC verdict for RTU)."""
        unit, tid, body = adu_parts(data, self.framing, self.unit)
        crc_ok = check_crc(data) if self.framing == "rtu" else None
        pdu = decode_pdu(body, self.direction is Direction.S2C)
        return [Frame(ts, self.stream, self.direction, unit, tid, pdu, data, crc_ok)]

    def flush(self, ts: float) -> list[Frame | Noise]:
        return []

    def reset(self, ts: float) -> list[Noise]:
        return []

    def tick(self, now: float) -> list[Frame | Noise]:
        return []

    def next_deadline(self) -> float | None:
        return None


class TypedFrameSource(BaseSource):
    """One frame's bytes (``framing``), a request unless ``response`` or the function
    code's exception bit say it is an answer."""

    mode: SourceMode = "file"

    def __init__(
        self, data: bytes, framing: Framing, *, response: bool = False, unit: int = 0
    ) -> None:
        super().__init__()
        if framing not in ("rtu", "tcp", "pdu"):
            raise ValueError(f"unknown framing {framing!r}")
        self.name = "typed bytes"
        self.data = bytes(data)
        self.framing = framing
        self.unit = unit
        body = adu_parts(self.data, framing, unit)[2]  # too few bytes: TypedFrameError
        self.response = response or bool(body and body[0] & 0x80)
        self.stream: Stream | None = None

    def open(self, hub: Hub) -> None:
        """Take a stream id (an untimed stream between ``client`` and ``server``) and
        name its decoder: the bytes are one ADU."""
        from mbmon.pipeline import DecoderEntry

        super().open(hub)
        transport = Transport.RTU if self.framing == "rtu" else Transport.TCP
        self.stream = Stream(hub.new_stream_id(), transport, "client", "server", timed=False)
        entry = DecoderEntry(self._decoder, datagram=True)
        hub.pipeline.use_decoder(self.stream, entry, report_unanswered=False)

    def _decoder(
        self, stream: Stream, direction: Direction, config: PipelineConfig
    ) -> StreamDecoding:
        return TypedAduDecoder(stream, direction, self.framing, self.unit)

    def items(self) -> Iterable[Item]:
        """The one chunk (ts 0.0, untimed), in the direction the bytes travel."""
        if self.stream is None:
            return ()
        direction = Direction.S2C if self.response else Direction.C2S
        return (Chunk(0.0, self.stream, direction, self.data),)
