"""Fixtures of the sink tests: real records from tests/sinks/sink_records.py."""

from __future__ import annotations

import pytest
from sink_records import REPO, run_pipeline, session_items

from mbmon.model import Chunk, Record


@pytest.fixture(scope="session")
def session_stream() -> list[Chunk | Record]:
    return run_pipeline(session_items())


@pytest.fixture(scope="session")
def hrss_stream() -> list[Chunk | Record]:
    from mbmon.cli import make_annotator
    from mbmon.sources.pcapfile import read_capture

    capture = REPO / "captures" / "hrss_ptp.pcap"
    if not capture.exists():
        pytest.skip("captures/hrss_ptp.pcap absent")
    return run_pipeline(list(read_capture(capture)), make_annotator(["hrss"]))
