"""The registry of stream decoders (mbmon.pipeline.DECODERS): the transport alone picks
a stream's decoder, so a new transport is one ``register_decoder`` call. A toy transport
registered here (a length-prefixed bus: [length][unit][PDU], no CRC) runs through the
pipeline and the hub into ``read``'s console, and every built-in transport has its entry."""

from __future__ import annotations

import io
from collections.abc import Iterator
from typing import ClassVar

import pytest

from mbmon.format import View
from mbmon.hub import Hub
from mbmon.model import Chunk, Direction, Frame, Noise, RecordKind, Stream, Transport
from mbmon.pipeline import (
    DECODERS,
    Pipeline,
    PipelineConfig,
    StreamDecoding,
    decoder_entry,
    register_decoder,
)
from mbmon.protocol.mbap import MbapDecoder
from mbmon.protocol.pdu import decode_pdu, encode_read_request, encode_read_response
from mbmon.protocol.rtu import RtuDecoder
from mbmon.sinks.console import ConsoleListener

TOY = "toy-length-bus"  # any hashable a source puts in Stream.transport


class LengthPrefixed:
    """A toy sans-I/O decoder: ``[n][unit][pdu (n - 1 bytes)]`` per ADU; the
    client's direction carries requests, the server's responses."""

    made: ClassVar[list[tuple[int, Direction]]] = []

    def __init__(self, stream: Stream, direction: Direction) -> None:
        self.stream = stream
        self.direction = direction
        self._held = bytearray()
        LengthPrefixed.made.append((stream.id, direction))

    @property
    def buffered(self) -> int:
        return len(self._held)

    def feed(self, data: bytes, ts: float) -> list[Frame | Noise]:
        self._held += data
        out: list[Frame | Noise] = []
        while self._held and len(self._held) >= 1 + self._held[0]:
            n = self._held[0]
            adu = bytes(self._held[: 1 + n])
            del self._held[: 1 + n]
            response = self.direction is Direction.S2C
            pdu = decode_pdu(adu[2:], response)
            out.append(Frame(ts, self.stream, self.direction, adu[1], None, pdu, adu))
        return out

    def flush(self, ts: float) -> list[Frame | Noise]:
        return self.reset(ts)  # type: ignore[return-value]

    def reset(self, ts: float) -> list[Noise]:
        held, self._held = bytes(self._held), bytearray()
        return [Noise(ts, self.stream, self.direction, held, "cut")] if held else []

    def tick(self, now: float) -> list[Frame | Noise]:
        return []

    def next_deadline(self) -> float | None:
        return None


def make_toy(stream: Stream, direction: Direction, config: PipelineConfig) -> StreamDecoding:
    return LengthPrefixed(stream, direction)


@pytest.fixture
def toy_registered() -> Iterator[None]:
    register_decoder(TOY, make_toy)
    try:
        yield
    finally:
        del DECODERS[TOY]


def adu(unit: int, pdu: bytes) -> bytes:
    return bytes((1 + len(pdu), unit)) + pdu


def test_a_registered_toy_transport_picks_its_decoder(toy_registered: None) -> None:
    LengthPrefixed.made.clear()
    stream = Stream(0, TOY, "toy-client", "toy-server")  # type: ignore[arg-type]
    out = io.StringIO()
    hub = Hub(Pipeline(), [ConsoleListener(out, View())])
    req = adu(7, encode_read_request(3, 0x10, 2))
    resp = adu(7, encode_read_response(3, [0x1234, 0x5678]))
    # split anywhere: the toy decoder gathers its ADUs like any stream decoder
    hub.run_items(
        [
            Chunk(1.0, stream, Direction.C2S, req[:3]),
            Chunk(1.001, stream, Direction.C2S, req[3:]),
            Chunk(1.01, stream, Direction.S2C, resp),
        ]
    )
    hub.close()
    assert LengthPrefixed.made == [(0, Direction.C2S), (0, Direction.S2C)]
    lines = out.getvalue().splitlines()
    assert len(lines) == 2
    assert "03 00 10 00 02" in lines[0]
    assert "03 04 12 34 56 78" in lines[1]
    assert "(9.0 ms)" in lines[1]  # paired by order like any stream without tids


def test_registering_a_datagram_transport_flushes_every_chunk(toy_registered: None) -> None:
    register_decoder(TOY, make_toy, datagram=True)
    stream = Stream(0, TOY, "toy-client", "toy-server")  # type: ignore[arg-type]
    pipe = Pipeline()
    # a datagram cut short is noise at once, not bytes held for the next datagram
    records = pipe.feed(Chunk(1.0, stream, Direction.C2S, adu(1, encode_read_request(3, 0, 1))[:4]))
    assert [r.kind for r in records] == [RecordKind.NOISE]
    assert pipe.next_deadline() is None


def test_an_unregistered_transport_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="no stream decoder is registered for transport 'nope'"):
        decoder_entry("nope")


@pytest.mark.parametrize(
    ("transport", "kind", "datagram"),
    [
        (Transport.TCP, MbapDecoder, False),
        (Transport.UDP, MbapDecoder, True),
        (Transport.RTU, RtuDecoder, False),
        (Transport.RTU_OVER_TCP, RtuDecoder, False),
        (Transport.RTU_OVER_UDP, RtuDecoder, True),
    ],
)
def test_every_builtin_transport_is_registered(
    transport: Transport, kind: type, datagram: bool
) -> None:
    entry = decoder_entry(transport)
    assert entry.datagram is datagram
    stream = Stream(0, transport, "a", "b")
    decoder = entry.make(stream, Direction.C2S, PipelineConfig(timeout=2.0, baudrate=9600))
    assert isinstance(decoder, kind)
    assert set(DECODERS) >= set(Transport)
