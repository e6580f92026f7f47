"""The core against the reference pipeline on every capture the project and others made."""

from __future__ import annotations

from pathlib import Path

import pytest
from core_diff import REAL, ROOT, assert_same, require_core

OWN = sorted((ROOT / "captures").glob("*.pcap*"))
PUBLIC = sorted(REAL.glob("*.pcap*")) if REAL.is_dir() else []
# captures the core must cover (it declines the others: RTU, noise, gaps, 5View)
COVERED = {"demo.pcap", "hrss_ptp.pcap", "sim_exceptions.pcap", "sim_functions.pcap"}


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


@pytest.mark.parametrize("path", OWN, ids=lambda p: p.name)
def test_own_captures(path: Path) -> None:
    assert_same(path, covered=True if path.name in COVERED else None)


@pytest.mark.parametrize("path", PUBLIC, ids=lambda p: p.name)
def test_public_captures(path: Path) -> None:
    assert_same(path)


def test_public_captures_present() -> None:
    if not PUBLIC:
        pytest.skip(f"{REAL} absent (../shared/captures/real)")
    covered = [p for p in PUBLIC if assert_same(p) is None]
    assert len(covered) >= len(PUBLIC) // 2, "the core declined most real captures"


def test_other_port_and_timeout() -> None:
    assert_same(ROOT / "captures" / "demo.pcap", timeout=0.001, covered=True)
    assert_same(ROOT / "captures" / "demo.pcap", ports=frozenset({502, 1502}), covered=True)
