"""The line sinks: .jsonl (= read --json), .csv (one row per frame), .txt (monitor lines)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sink_records import feed

from mbmon.format import View, json_line, record_line, record_to_json
from mbmon.hub import hooks_of
from mbmon.model import Chunk, Record, RecordKind
from mbmon.sinks.base import SinkContext, SinkError, open_sink
from mbmon.sinks.csvfile import COLUMNS, CsvSink, utc_text
from mbmon.sinks.jsonl import JsonlSink, dumps_line
from mbmon.sinks.text import TextSink
from mbmon.stored import StoredRecord, kind_of

CTX = SinkContext(view=View(robot="192.168.0.10"), source="x.pcap")


def records_of(stream: list[Chunk | Record]) -> list[Record]:
    return [x for x in stream if isinstance(x, Record)]


def test_jsonl_lines_are_read_json_lines(tmp_path: Path, session_stream: list) -> None:
    path = tmp_path / "out.jsonl"
    with open_sink(path, CTX) as sink:
        assert isinstance(sink, JsonlSink)
        feed(sink, session_stream)
    lines = path.read_text("utf-8").splitlines()
    recs = records_of(session_stream)
    # the encoder of `read --json` (mbmon.cli.emit_records)
    assert lines == [json_line(record_to_json(r, CTX.view)) for r in recs]
    assert [json.loads(line) for line in lines] == [
        json.loads(json.dumps(record_to_json(r, CTX.view))) for r in recs
    ]
    assert json.loads(lines[1])["line"].split("  ")[1] == "Receive from client"


@pytest.mark.parametrize("robot", [None, "127.0.0.1:502"], ids=["neutral-labels", "robot-labels"])
def test_jsonl_bytes_with_profile_and_non_ascii(tmp_path: Path, hrss_stream: list, robot) -> None:
    """The HRSS capture through the HRSS profile: device notes, robot state, commands and
    non-ASCII text (the neutral labels' arrow, degree signs in notes), written as the UTF-8
    bytes of ``json_line(record_to_json(...))`` with one newline each."""
    view = View(robot=robot)
    ctx = SinkContext(view=view, source="captures/hrss_ptp.pcap")
    path = tmp_path / "h.jsonl"
    with open_sink(path, ctx) as sink:
        feed(sink, hrss_stream)
    recs = records_of(hrss_stream)
    expect = "".join(json_line(record_to_json(r, View(robot=robot))) + "\n" for r in recs)
    data = path.read_bytes()
    assert data == expect.encode("utf-8")
    assert any(r.notes for r in recs) and any(r.kind is RecordKind.COMMAND for r in recs)
    assert "°" in expect
    assert ("→" in expect) is (robot is None)
    labels = {json.loads(line)["line"].split("  ")[1] for line in data.splitlines()}
    assert ("Receive from client" in labels) is (robot is not None)


def test_text_lines_are_console_lines(tmp_path: Path, session_stream: list) -> None:
    path = tmp_path / "out.txt"
    with open_sink(path, CTX) as sink:
        assert isinstance(sink, TextSink)
        feed(sink, session_stream)
    lines = path.read_text("utf-8").splitlines()
    assert lines == [record_line(r, CTX.view) for r in records_of(session_stream)]
    assert any("02 01 2C 00 05" in line for line in lines)  # manual §5.5.2.2
    assert any("Send to client" in line and "10 00 C9 00 03" in line for line in lines)


def test_csv_one_row_per_frame(tmp_path: Path, session_stream: list) -> None:
    path = tmp_path / "out.csv"
    with open_sink(path, CTX) as sink:
        assert isinstance(sink, CsvSink)
        feed(sink, session_stream)
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    recs = [r for r in records_of(session_stream) if r.kind is not RecordKind.EVENT]
    assert len(rows) == len(recs)
    assert list(rows[0]) == list(COLUMNS)
    by_pdu = {row["pdu"]: row for row in rows}
    read = by_pdu["02 01 2C 00 05"]
    assert (read["fc"], read["address"], read["count"], read["unit"]) == ("2", "300", "5", "1")
    assert read["kind"] == "request" and read["tid"] == "1" and read["crc_ok"] == ""
    write = by_pdu["10 00 C9 00 03 06 00 6F 00 DE 01 4D"]
    assert write["values"] == "111 222 333"
    exc = by_pdu["83 02"]
    assert (exc["kind"], exc["exception_code"], exc["fc"]) == ("exception", "2", "3")
    response = by_pdu["02 01 13"]
    assert response["request_index"] == read["index"] and float(response["latency_ms"]) == 10.0
    noise = [row for row in rows if row["kind"] == "noise"]
    assert len(noise) == 2 and "CRC" in noise[1]["malformed"]
    rtu = by_pdu["03 04 00 01 00 02"]
    assert rtu["crc_ok"] == "true" and rtu["transport"] == "rtu" and rtu["tid"] == ""
    assert read["utc"] == utc_text(float(read["time"]))
    assert read["utc"].startswith("2023-11-14T22:13:20.") and read["utc"].endswith("Z")
    assert read["notes"].startswith("Read Discrete Inputs 300..304")


def test_stored_records_write_what_the_records_write(tmp_path: Path, session_stream: list) -> None:
    """A record read back from a log (``mbmon export``: its stored object and line, as a
    :class:`StoredRecord`) through the same hook gives the file the record gave."""
    recs = records_of(session_stream)
    objs = [json.loads(dumps_line(record_to_json(r, CTX.view))) for r in recs]
    stored = [
        StoredRecord(o["index"], r.ts, kind_of(o), None, obj=o, line=o["line"])
        for o, r in zip(objs, recs, strict=True)
    ]
    for suffix in (".jsonl", ".csv", ".txt"):
        direct, made = tmp_path / f"a{suffix}", tmp_path / f"b{suffix}"
        with open_sink(direct, CTX) as sink:
            feed(sink, session_stream)
        with open_sink(made, CTX) as sink:
            hooks_of(sink).records(stored)
        assert made.read_bytes() == direct.read_bytes(), suffix


def test_unknown_suffix_and_unwritable_path(tmp_path: Path) -> None:
    with pytest.raises(SinkError, match="unknown output format"):
        open_sink(tmp_path / "x.xlsx", CTX)
    with pytest.raises(SinkError, match="cannot write"):
        open_sink(tmp_path / "missing-dir" / "x.jsonl", CTX)


# --------------------------------------------------------------------------- hostile times


def _retimed(stream: list[Chunk | Record], ts: float) -> list[Chunk | Record]:
    """The session with every time replaced by ``ts`` (a damaged capture's)."""
    import dataclasses

    return [dataclasses.replace(x, ts=ts) for x in stream]


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.sampled_from([1e17, 1.8e19, 1.7e12, -1e12, -(2.0**63), 2.0**64]),
    )
)
def test_fuzz_every_line_sink_writes_any_time(session_stream: list, ts: float) -> None:
    """A record with any timestamp is written by .jsonl, .csv and .txt
    (times print as epoch seconds where no calendar shows them), never raises."""
    import tempfile

    stream = _retimed(session_stream, ts)
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in (".jsonl", ".csv", ".txt"):
            path = Path(tmp) / f"x{suffix}"
            with open_sink(path, CTX) as sink:
                feed(sink, stream)
            text = path.read_text("utf-8")
            assert text
        rows = list(csv.DictReader((Path(tmp) / "x.csv").open(newline="", encoding="utf-8")))
        assert rows and all(row["utc"] for row in rows)
        jsonl = (Path(tmp) / "x.jsonl").read_text("utf-8").splitlines()
        assert len(jsonl) == len(records_of(stream))
        for line in jsonl:
            json.loads(line)
