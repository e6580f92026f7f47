"""The core's log blocks reach zstd without a copy.

The core writes a log's message records into a bytes object and hands that very
object to the sink (``McapSink.put_packed``); the sink's chunk of one block is that
object too (``b"".join`` of one part returns it), so zstd reads the bytes where the
core wrote them. Checked by address: the memory the core last wrote a block into
(``_reader._last_block_at``) must be the handed-over bytes object's own data, and
the object zstd compresses must be that same object. A copy anywhere on the way (the
core's ``PyBytes_FromStringAndSize`` of its buffer, a join, a ``bytes()``) fails it.
The bytes object a block is written in (``Buf.box``) is held to what was written
into it, grown or not, through a test-only entry.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from core_diff import require_core
from gen import polling_capture
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_diff import _context

from mbmon import core
from mbmon.format import View
from mbmon.sinks.mcap import McapSink
from mbmon.timefmt import TimeFormat

PAIRS = 6_000  # about 8 MiB of message records: several blocks of about 1 MiB
DATA_AT = bytes.__basicsize__ - 1  # where a bytes object's data starts (CPython)


def _capture(tmp: Path) -> Path:
    return polling_capture(tmp / "many.pcap", PAIRS)


def test_blocks_reach_zstd_where_the_core_wrote_them(tmp_path: Path) -> None:
    require_core()
    from mbmon.core import _reader

    path = _capture(tmp_path)
    log = tmp_path / "x.mcap"
    view = View(time_format=TimeFormat("a"))
    handed: list[tuple[bytes, int]] = []  # each block, and where the core wrote it
    compressed: list[Any] = []  # what zstd was given
    sinks: list[McapSink] = []

    def open_log() -> McapSink:
        sink = McapSink(log, _context(path, view, 1.0))
        put_packed, writer = sink.put_packed, sink._log.writer
        compress = writer._compress
        assert compress is not None and writer.compression == "zstd"

        def put(data: bytes, first: int, last: int, totals: Any) -> None:
            handed.append((data, _reader._last_block_at()))
            put_packed(data, first, last, totals)

        def squeeze(data: bytes) -> bytes:
            compressed.append(data)
            return compress(data)

        sink.put_packed = put  # type: ignore[method-assign]
        writer._compress = squeeze
        sinks.append(sink)
        return sink

    run = core.read_file(
        str(path),
        ports=frozenset({502}),
        timeout=1.0,
        view=view,
        as_json=False,
        write=None,
        log=open_log,
    )
    assert run.declined is None and len(sinks) == 1
    whole = [data for data, _ in handed[:-1]]  # the last block is the run's short rest
    assert len(whole) >= 4, f"{len(handed)} blocks: the capture is too small"
    for i, (data, at) in enumerate(handed[:-1]):
        assert len(data) >= 1 << 20, f"block {i}: {len(data)} bytes"
        assert at == id(data) + DATA_AT, f"block {i} was copied before the sink got it"
    # every whole block is a chunk of its own, compressed from the very object handed over
    for data in whole:
        assert any(c is data for c in compressed), "a block was copied on its way to zstd"
    with open(log, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        messages = sum(1 for _ in reader.iter_messages(log_time_order=False))
    assert messages == summary.statistics.message_count > 3 * PAIRS
    assert len(summary.chunk_indexes) >= len(whole)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.binary(max_size=300), max_size=40),
    st.integers(min_value=1, max_value=512),
)
def test_a_boxed_buffer_hands_over_what_was_written(pieces: list[bytes], room: int) -> None:
    """A block's bytes object (``Buf.box``) grows like any buffer (a larger object, what
    was written copied in) and is handed over cut to its length, in place."""
    require_core()
    from mbmon.core import _reader

    data, _ = _reader._boxed(pieces, room)
    assert type(data) is bytes and data == b"".join(pieces)
    assert hash(data) == hash(b"".join(pieces))  # an ordinary bytes object


def test_a_grown_block_is_cut_where_it_was_written() -> None:
    """A block's size (the C library's memory, not Python's small-object arenas): grown
    past its room once, then cut to its length in place, not copied."""
    require_core()
    from mbmon.core import _reader

    pieces = [bytes([i]) * (64 << 10) for i in range(9)]  # 576 KiB into 512 KiB of room
    data, at = _reader._boxed(pieces, 512 << 10)
    assert data == b"".join(pieces)
    assert at == id(data) + DATA_AT
