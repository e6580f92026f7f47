"""Raw RTU bus dumps (mbmon.sources.rawfile)."""

from __future__ import annotations

from pathlib import Path

import pytest

from mbmon.model import Direction, Transport
from mbmon.sources.pcapfile import CaptureError
from mbmon.sources.rawfile import read_rtu_raw

# Read Holding Registers, slave 1, 2 registers at 0 (CRC C40B), and its answer.
BUS = bytes.fromhex("010300000002c40b") + bytes.fromhex("010304000700084a34")


def test_chunks_cover_the_file_in_order(tmp_path: Path) -> None:
    path = tmp_path / "bus.bin"
    path.write_bytes(BUS)
    chunks = list(read_rtu_raw(path, chunk_size=5))
    assert [len(c.data) for c in chunks] == [5, 5, 5, 2]
    assert b"".join(c.data for c in chunks) == BUS
    stream = chunks[0].stream
    assert (stream.id, stream.transport, stream.client, stream.server) == (
        0,
        Transport.RTU,
        "bus.bin",
        "bus.bin",
    )
    assert {(c.direction, c.ts, c.stream) for c in chunks} == {(Direction.BUS, 0.0, stream)}


def test_empty_file_gives_nothing(tmp_path: Path) -> None:
    path = tmp_path / "empty.bin"
    path.write_bytes(b"")
    assert list(read_rtu_raw(path)) == []


def test_missing_file_raises_at_once(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="cannot open"):
        read_rtu_raw(tmp_path / "absent.bin")


def test_chunk_size_must_be_positive(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="chunk_size"):
        read_rtu_raw(tmp_path / "x", chunk_size=0)
