"""The sink tests' real records (tests/sinks/conftest.py), shared with the reader tests."""

from __future__ import annotations

import importlib.util
from pathlib import Path

_spec = importlib.util.spec_from_file_location(
    "mbmon_test_records", Path(__file__).resolve().parents[1] / "sinks" / "conftest.py"
)
assert _spec is not None and _spec.loader is not None
records = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(records)

session_stream = records.session_stream
hrss_stream = records.hrss_stream
