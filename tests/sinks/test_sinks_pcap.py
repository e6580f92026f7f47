"""The pcap sink: TCP re-wrapped with consistent numbering, RTU as link type 147.

Checked two ways: read back by mbmon's own capture reader (records identical to
the originals), and dissected by tshark (function codes and reference numbers
agree; skipped when tshark is absent).
"""

from __future__ import annotations

import shutil
import struct
import subprocess
from pathlib import Path

import pytest
from sink_records import feed, run_pipeline

from mbmon.format import View, record_to_json
from mbmon.io.pcap import LINKTYPE_ETHERNET, LINKTYPE_USER0
from mbmon.model import Chunk, Record, RecordKind
from mbmon.sinks.base import SinkContext, open_sink
from mbmon.sinks.pcap import PcapSink
from mbmon.sources.pcapfile import read_capture

CTX = SinkContext(view=View(), source="x")


def linktype(path: Path) -> int:
    return int(struct.unpack("<I", path.read_bytes()[20:24])[0])


def frames_json(stream: list[Chunk | Record]) -> list[dict]:
    """read --json objects, times to the microsecond (pcap's resolution), line text left out."""
    out = []
    for x in stream:
        if isinstance(x, Record):
            obj = record_to_json(x, View())
            obj["time"] = round(obj["time"], 6)
            del obj["line"]
            out.append(obj)
    return out


def test_tcp_and_rtu_round_trip_through_mbmon_reader(tmp_path: Path, session_stream: list) -> None:
    path = tmp_path / "s.pcap"
    with open_sink(path, CTX) as sink:
        assert isinstance(sink, PcapSink)
        feed(sink, session_stream)
    assert sink.companion == tmp_path / "s.rtu.pcap"
    assert linktype(path) == LINKTYPE_ETHERNET
    assert linktype(sink.companion) == LINKTYPE_USER0
    original = [
        o for o in frames_json(session_stream) if o["transport"] == "tcp" or o["kind"] == "event"
    ]
    original = [o for o in original if o["stream"] == 0]
    again = frames_json(run_pipeline(list(read_capture(path))))
    assert again == original  # same endpoints, times, bytes, connect/disconnect: same records
    rtu_orig = [
        (o["kind"], o["unit"], o["pdu"]) for o in frames_json(session_stream) if o["stream"] == 1
    ]
    rtu_again = [
        (o["kind"], o["unit"], o["pdu"])
        for o in frames_json(run_pipeline(list(read_capture(sink.companion))))
        if o["kind"] != "event"
    ]
    assert rtu_again == rtu_orig


def test_hrss_capture_round_trip(tmp_path: Path, hrss_stream: list) -> None:
    path = tmp_path / "h.pcap"
    with PcapSink(path, CTX) as sink:
        feed(sink, hrss_stream)
    assert sink.companion is None and sink.skipped == 0
    plain = [x for x in hrss_stream if isinstance(x, Chunk)]
    again = [x for x in read_capture(path) if isinstance(x, Chunk)]
    assert [(c.ts, c.direction, c.data, c.stream) for c in again] == [
        (c.ts, c.direction, c.data, c.stream) for c in plain
    ]


def test_empty_session_gives_a_valid_empty_capture(tmp_path: Path) -> None:
    path = tmp_path / "e.pcap"
    PcapSink(path, CTX).close()
    assert path.stat().st_size == 24 and linktype(path) == LINKTYPE_ETHERNET
    assert list(read_capture(path)) == []


@pytest.mark.skipif(shutil.which("tshark") is None, reason="tshark not installed")
def test_tshark_decodes_the_rewrapped_tcp(tmp_path: Path, hrss_stream: list) -> None:
    path = tmp_path / "t.pcap"
    with PcapSink(path, CTX) as sink:
        feed(sink, hrss_stream)
    fields = ["-e", "modbus.func_code", "-e", "modbus.reference_num", "-e", "tcp.analysis.flags"]
    out = subprocess.run(
        ["tshark", "-r", str(path), "-Y", "modbus", "-T", "fields", *fields],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    rows = [line.split("\t") for line in out.splitlines()]
    assert rows, "tshark found no Modbus"
    assert all(not flags for _, _, flags in rows), "TCP analysis warnings (bad numbering)"
    fcs = [int(fc) for fc_field, _, _ in rows for fc in fc_field.split(",") if fc]
    recs = [x for x in hrss_stream if isinstance(x, Record) and x.frame is not None]
    assert fcs == [r.frame.pdu.fc for r in recs if r.frame is not None]  # exception bit cleared
    requests = [
        r.frame.pdu.address for r in recs if r.kind is RecordKind.REQUEST and r.frame is not None
    ]
    refs = [int(row[1]) for row, r in zip(rows, recs, strict=True) if r.kind is RecordKind.REQUEST]
    assert refs == requests
