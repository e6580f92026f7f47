"""Raw RS485 bus dumps: a file of bytes exactly as read from a Modbus RTU line.

This module owns turning such a file (``cat /dev/ttyUSB0 > bus.bin``, a logic
analyser export, a serial sniffer's binary log) into chunks of one RTU bus
stream. The file has no timestamps: the stream is marked untimed
(``Stream.timed`` is ``False``), every chunk has ``ts`` 0.0 as a placeholder
(lines show record numbers ``#N`` instead of times, no latency is shown, the
JSON ``time`` and ``latency_ms`` are null), and framing relies on length
prediction and CRC alone (silence gaps are unknown).
"""

from __future__ import annotations

from collections.abc import Iterator
from io import BufferedReader
from pathlib import Path

from mbmon.model import Chunk, Direction, Stream, Transport
from mbmon.sources.pcapfile import CaptureError

__all__ = ["read_rtu_raw"]


def read_rtu_raw(
    path: str | Path, chunk_size: int = 4096, *, stream_id: int = 0
) -> Iterator[Chunk]:
    """Chunks of at most ``chunk_size`` bytes of the file, in order, on one stream
    ``Stream(stream_id, Transport.RTU, name, name, timed=False)`` (``name`` = the file
    name), direction BUS, ts 0.0. Raises :class:`CaptureError` at once if the file
    cannot be opened."""
    if chunk_size < 1:
        raise ValueError("chunk_size must be at least 1")
    path = Path(path)
    try:
        f: BufferedReader = open(path, "rb")
    except OSError as exc:
        raise CaptureError(f"{path}: cannot open ({exc.strerror or exc})") from None
    stream = Stream(stream_id, Transport.RTU, path.name, path.name, timed=False)
    return _chunks(f, stream, chunk_size)


def _chunks(f: BufferedReader, stream: Stream, chunk_size: int) -> Iterator[Chunk]:
    with f:
        while data := f.read1(chunk_size):  # a pipe or a pty: what is there, as it comes
            yield Chunk(0.0, stream, Direction.BUS, data)
