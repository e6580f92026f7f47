"""An MCAP log whose chunks are written by the caller's thread (``McapSink.write_here``,
the compiled core's way) and fed message records made elsewhere (``put_packed``):
the writer thread is gone, each closed chunk is on disk when ``move`` returns, a
signal during a chunk's write waits until the chunk is whole, and the file reads
back with the messages and counters it was given."""

from __future__ import annotations

import itertools
import signal
import threading
from pathlib import Path

import pytest
from mcap.reader import make_reader

from mbmon.format import View
from mbmon.io.mcap.layout import Totals
from mbmon.model import Chunk, Direction, Stream, Transport
from mbmon.sinks.base import SinkContext
from mbmon.sinks.mcap import McapSink

CTX = SinkContext(view=View(), command_line=["mbmon"], source="x.pcap")
STREAM = Stream(0, Transport.TCP, "10.0.0.1:40000", "10.0.0.2:502")
T0 = 1_700_000_000.0


def _block(sink: McapSink, start: int, n: int, totals: Totals) -> tuple[bytes, int, int, Totals]:
    """``n`` chunks' /modbus/raw message records as the layout makes them."""
    chunks = [
        Chunk(T0 + (start + i) * 0.001, STREAM, Direction.C2S, bytes([i & 255]) * 40)
        for i in range(n)
    ]
    records, first, last, new = sink.layout.convert(chunks, totals)
    return b"".join(records), first, last, new


def _writer_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "mbmon-mcap-writer"]


def test_chunks_are_written_by_the_caller(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    before = len(_writer_threads())
    sink = McapSink(path, CTX, chunk_size=4096)
    assert len(_writer_threads()) == before + 1
    sink.write_here()
    sink.write_here()  # idempotent
    assert len(_writer_threads()) == before
    totals = sink.layout.new_totals()
    sizes = []
    for k in range(20):
        data, first, last, totals = _block(sink, 50 * k, 50, totals)
        sink.put_packed(data, first, last, totals.copy())
        sizes.append(path.stat().st_size)  # each block closed a chunk, on disk now
    assert all(b > a for a, b in itertools.pairwise(sizes))
    sink.close()
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        got = [m for _s, ch, m in reader.iter_messages(log_time_order=False)]
        stats = reader.get_summary().statistics  # type: ignore[union-attr]
    assert len(got) == 1000  # the chunks (no record: no stats event)
    assert stats.message_count == 1000 and stats.chunk_count >= 20
    assert stats.channel_message_counts[sink.layout.channels["/modbus/raw"]] == 1000


def test_a_signal_during_a_chunk_write_waits_for_the_chunk(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    sink = McapSink(path, CTX, chunk_size=4096)
    sink.write_here()
    writer = sink._log.writer
    real_write = writer.write_chunk
    interrupted_inside: list[bool] = []

    def write_chunk(chunk: object) -> None:
        signal.raise_signal(signal.SIGINT)  # arrives in the middle of the write
        interrupted_inside.append(True)  # ... and is held back: the write goes on
        real_write(chunk)  # type: ignore[arg-type]

    writer.write_chunk = write_chunk  # type: ignore[method-assign]
    totals = sink.layout.new_totals()
    data, first, last, totals = _block(sink, 0, 200, totals)
    with pytest.raises(KeyboardInterrupt):
        sink.put_packed(data, first, last, totals.copy())
    assert interrupted_inside == [True]
    writer.write_chunk = real_write  # type: ignore[method-assign]
    sink.close()
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        n = sum(1 for _ in reader.iter_messages(log_time_order=False))
    assert n == 200  # the whole chunk
