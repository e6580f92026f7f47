"""Helpers of the monitor's tests: real captures through the real pipeline.

A module of its own name: `conftest` is a name several test folders share.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from mbmon.model import Chunk, Event, Record

REPO = Path(__file__).resolve().parents[2]


def hrss_items() -> list[Chunk | Event]:
    """The HRSS capture the project made with its simulator (captures/hrss_ptp.pcap)."""
    from mbmon.sources.pcapfile import read_capture

    capture = REPO / "captures" / "hrss_ptp.pcap"
    if not capture.exists():
        pytest.skip("captures/hrss_ptp.pcap absent")
    return list(read_capture(capture))


def records_of(items: list[Chunk | Event], profiles: list[str]) -> list[Record]:
    """The records of ``items`` through a pipeline with ``profiles`` (finished)."""
    from mbmon.commands.common import make_annotator
    from mbmon.pipeline import Pipeline

    pipeline = Pipeline(make_annotator(profiles))
    out = [r for item in items for r in pipeline.feed(item)]
    return out + pipeline.finish()
