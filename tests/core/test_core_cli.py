"""The wiring: ``mbmon --version`` names the active core, ``read --debug-core`` says
which path ran, and ``MBMON_NO_EXTENSIONS=1`` runs the Python pipeline with the same
bytes on stdout and stderr."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from core_diff import ROOT, require_core

DEMO = ROOT / "captures" / "demo.pcap"
RTU = ROOT / "captures" / "sim_rtu.pcap"


def _mbmon(*args: str, pure: bool = False) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ)
    env.pop("MBMON_NO_EXTENSIONS", None)
    if pure:
        env["MBMON_NO_EXTENSIONS"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "mbmon", *args], capture_output=True, env=env, cwd=ROOT,
        timeout=120,
    )  # fmt: skip


def test_version_names_the_core() -> None:
    pure = _mbmon("--version", pure=True)
    assert pure.returncode == 0
    assert b"core: pure Python (MBMON_NO_EXTENSIONS is set)" in pure.stdout
    require_core()
    assert b"core: compiled" in _mbmon("--version").stdout


@pytest.mark.parametrize("fmt", [[], ["--json"]])
def test_read_same_bytes_either_way(fmt: list[str]) -> None:
    require_core()
    fast = _mbmon("read", str(DEMO), "--debug-core", *fmt)
    pure = _mbmon("read", str(DEMO), "--debug-core", *fmt, pure=True)
    assert fast.returncode == pure.returncode == 0
    assert b"core: the compiled core read the input" in fast.stderr
    assert b"core: declined (the compiled core is unavailable" in pure.stderr
    assert fast.stdout == pure.stdout
    assert fast.stderr.splitlines()[1:] == pure.stderr.splitlines()[1:]  # the summary


def test_declines_are_visible_and_change_nothing() -> None:
    require_core()
    rtu = _mbmon("read", str(RTU), "--debug-core")
    assert b"core: declined (link type 147)" in rtu.stderr
    assert rtu.stdout == _mbmon("read", str(RTU), pure=True).stdout
    robot = _mbmon("read", str(DEMO), "--robot", "127.0.0.1:502", "--debug-core")
    assert b"core: declined (--robot is not covered by the core)" in robot.stderr
    count = _mbmon("read", str(DEMO), "-c", "3", "--debug-core")
    assert b"core: declined (-c is not covered" in count.stderr
    assert len(count.stdout.splitlines()) == 3
