"""Fixtures of the log reader tests: the sink tests' real records (tests/sinks/sink_records.py)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

from mbmon.model import Chunk, Record

if "sink_records" not in sys.modules:
    _spec = importlib.util.spec_from_file_location(
        "sink_records", Path(__file__).resolve().parents[1] / "sinks" / "sink_records.py"
    )
    assert _spec is not None and _spec.loader is not None
    _module = importlib.util.module_from_spec(_spec)
    sys.modules["sink_records"] = _module
    _spec.loader.exec_module(_module)

import sink_records


@pytest.fixture(scope="session")
def session_stream() -> list[Chunk | Record]:
    return sink_records.run_pipeline(sink_records.session_items())


@pytest.fixture(scope="session")
def hrss_stream() -> list[Chunk | Record]:
    from mbmon.cli import make_annotator
    from mbmon.sources.pcapfile import read_capture

    capture = sink_records.REPO / "captures" / "hrss_ptp.pcap"
    if not capture.exists():
        pytest.skip("captures/hrss_ptp.pcap absent")
    return sink_records.run_pipeline(list(read_capture(capture)), make_annotator(["hrss"]))
