"""The bytes of one frame typed by hand (``mbmon decode``) as a source of the hub.

:class:`TypedFrameSource` implements the source contract (:mod:`mbmon.sources.base`):
its one chunk goes through the same stream decoder, pairing and annotation as a
capture's, so the frame is decoded, annotated and written by the same code
(``format.py``'s lines and JSON record). The framing is the caller's to decide
(``rtu``: unit, PDU, CRC; ``tcp``: an MBAP header; ``pdu``: a bare PDU, wrapped
in an MBAP header with transaction id 0 and ``unit``); the direction says
whether the bytes are a request (client to server) or a response. The stream is
untimed: no time or latency is shown. An RTU frame whose CRC fails comes out as
a noise record with the decoder's reason, as it would on a bus.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING, Literal

from mbmon.model import Chunk, Direction, Stream, Transport
from mbmon.protocol.mbap import encode_adu
from mbmon.sources.base import BaseSource, SourceMode

if TYPE_CHECKING:
    from mbmon.hub import Hub, Item

__all__ = ["Framing", "TypedFrameSource"]

Framing = Literal["rtu", "tcp", "pdu"]


class TypedFrameSource(BaseSource):
    """One frame's bytes (``framing``), a request unless ``response``."""

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
        self.response = response
        self.unit = unit
        self.stream: Stream | None = None

    def open(self, hub: Hub) -> None:
        """Take a stream id: an untimed stream between ``client`` and ``server``."""
        super().open(hub)
        transport = Transport.RTU if self.framing == "rtu" else Transport.TCP
        self.stream = Stream(hub.new_stream_id(), transport, "client", "server", timed=False)

    def items(self) -> Iterable[Item]:
        """The one chunk (ts 0.0, untimed), in the direction the bytes travel."""
        if self.stream is None:
            return ()
        data = self.data
        if self.framing == "pdu":
            data = encode_adu(0, self.unit, data)
        direction = Direction.S2C if self.response else Direction.C2S
        return (Chunk(0.0, self.stream, direction, data),)
