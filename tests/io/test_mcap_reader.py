"""The tolerant MCAP reader: indexed read, recovery of unfinished files, clear errors."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
import sink_records as records
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from mbmon.format import View
from mbmon.io.mcap.reader import LogError, McapLog
from mbmon.sinks.base import SinkContext
from mbmon.sinks.mcap import McapSink

CTX = SinkContext(view=View(), command_line=["mbmon", "read", "x"], source="x")


@pytest.fixture(scope="module")
def log_bytes(
    tmp_path_factory: pytest.TempPathFactory, session_stream: list, hrss_stream: list
) -> bytes:
    """A finished log with many small chunks."""
    path = tmp_path_factory.mktemp("log") / "many.mcap"
    with McapSink(path, CTX, chunk_size=400) as sink:
        records.feed(sink, session_stream)
        records.feed(sink, hrss_stream)
    return path.read_bytes()


def expected(data: bytes, tmp: Path) -> list[tuple[str, int, bytes]]:
    """Every message, in file order, as the mcap package reads it."""
    path = tmp / "ref.mcap"
    path.write_bytes(data)
    with open(path, "rb") as f:
        return [
            (ch.topic, m.log_time, m.data)
            for _, ch, m in make_reader(f, validate_crcs=True).iter_messages(log_time_order=False)
        ]


def read_all(path: Path) -> tuple[McapLog, list[tuple[str, int, bytes]]]:
    log = McapLog(path)
    with log:
        got = [(m.topic, m.log_time, m.raw) for m in log.messages()]
    return log, got


def test_finished_file_is_read_through_its_index(tmp_path: Path, log_bytes: bytes) -> None:
    path = tmp_path / "f.mcap"
    path.write_bytes(log_bytes)
    log, got = read_all(path)
    assert log.finished and log.status.stopped_at is None
    assert got == expected(log_bytes, tmp_path)
    assert log.status.messages == len(got)
    assert log.status.describe() == f"finished log, {len(got)} messages"
    assert sum(log.topics.values()) == len(got)
    assert log.metadata["mbmon"]["source"] == "x"
    # topic filter: only chunks holding those topics are read, same messages
    with McapLog(path) as again:
        monitor = [m.raw for m in again.messages(["/modbus/monitor"])]
    assert monitor == [raw for topic, _, raw in got if topic == "/modbus/monitor"]


def test_every_truncation_recovers_a_prefix(tmp_path: Path, log_bytes: bytes) -> None:
    """Cut anywhere (a killed writer, a full disk): the complete chunks before the cut come back."""
    full = expected(log_bytes, tmp_path)
    summary_start = struct.unpack_from("<Q", log_bytes, len(log_bytes) - 8 - 20)[0]
    previous = -1
    cuts = sorted({*range(8, summary_start + 40, 37), summary_start - 1, summary_start})
    for cut in cuts:
        path = tmp_path / "cut.mcap"
        path.write_bytes(log_bytes[:cut])
        if cut < 8:
            continue
        log, got = read_all(path)
        assert not log.finished
        assert got == full[: len(got)], f"cut at {cut}: not a prefix"
        assert len(got) >= previous, f"cut at {cut}: fewer messages than a shorter file"
        previous = len(got)
        if cut < summary_start:
            assert log.status.stopped_at is not None and log.status.stopped_at <= cut
            assert "not finished" in log.status.describe()
    assert previous == len(full)  # cut right before the summary: everything is there


def test_zero_filled_tail(tmp_path: Path, log_bytes: bytes) -> None:
    summary_start = struct.unpack_from("<Q", log_bytes, len(log_bytes) - 8 - 20)[0]
    path = tmp_path / "zeros.mcap"
    path.write_bytes(log_bytes[: summary_start - 1] + bytes(4096))
    log, got = read_all(path)
    assert not log.finished and got
    assert log.status.problem is not None


def test_header_only(tmp_path: Path) -> None:
    path = tmp_path / "h.mcap"
    sink = McapSink(path, CTX)
    data = path.read_bytes()  # a writer killed before any record
    sink.close()
    path.write_bytes(data)
    log, got = read_all(path)
    assert got == [] and not log.finished
    assert log.metadata["mbmon"]["source"] == "x"


def test_damaged_chunk_is_a_clear_error(tmp_path: Path, log_bytes: bytes) -> None:
    ref = expected(log_bytes, tmp_path)
    with open(tmp_path / "ref.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    third = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[2]
    damaged = bytearray(log_bytes)
    damaged[third.chunk_start_offset + third.chunk_length - 3] ^= 0x55  # inside compressed data
    path = tmp_path / "bad.mcap"
    path.write_bytes(bytes(damaged))
    got = []
    with McapLog(path) as log, pytest.raises(LogError) as err:
        for m in log.messages():
            got.append((m.topic, m.log_time, m.raw))
    text = str(err.value)
    assert f"chunk at byte {third.chunk_start_offset}" in text
    assert "everything readable shown" in text
    with McapLog(tmp_path / "ref.mcap") as log:  # the messages of the damaged chunk
        lost = [(m.topic, m.log_time, m.raw) for m in log._parse_records(
            log._chunk_records(log._layout.chunks[2]), third.chunk_start_offset)]  # fmt: skip
    assert lost and got == [m for m in ref if m not in lost]  # every other chunk is read


@pytest.mark.parametrize(
    ("content", "message"),
    [(b"", "empty file"), (b"PK\x03\x04 not mcap at all", "not an MCAP file")],
)
def test_not_a_log(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    with pytest.raises(LogError, match=message):
        McapLog(path)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(LogError, match="cannot open"):
        McapLog(tmp_path / "nope.mcap")


@settings(
    max_examples=200,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(data=st.data())
def test_damage_never_raises_anything_but_log_error(
    tmp_path: Path, log_bytes: bytes, data: st.DataObject
) -> None:
    raw = bytearray(log_bytes[: data.draw(st.integers(0, len(log_bytes)))])
    for _ in range(data.draw(st.integers(0, 4))):
        if raw:
            at = data.draw(st.integers(0, len(raw) - 1))
            raw[at] = data.draw(st.integers(0, 255))
    path = tmp_path / "fuzz.mcap"
    path.write_bytes(bytes(raw))
    try:
        with McapLog(path) as log:
            for m in log.messages():
                assert isinstance(m.raw, bytes)
            log.status.describe()
    except LogError:
        pass
