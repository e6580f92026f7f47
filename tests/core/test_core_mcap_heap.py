"""A log written by the core reuses its memory: writing ``-w x.mcap`` next to ``-q``
costs a handful of page faults, not fresh zeroed pages for every block, chunk and
compressed chunk (about 0.14 per ADU when glibc maps and trims them each time).

Page faults are counted by the kernel for the child (``wait4``'s ``ru_minflt``): a
count, not a time, so the check does not depend on the machine's load."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from core_diff import ROOT, require_core
from gen import polling_capture

ENV = {**os.environ, "PYTHONPATH": str(ROOT), "TZ": "UTC"}
PAIRS = 40_000


def _faults(args: list[str]) -> int:
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "read", *args],
        cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    _, status, usage = os.wait4(proc.pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, proc.stderr.read() if proc.stderr else ""
    return usage.ru_minflt


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's heap tuning")
def test_log_blocks_reuse_memory(tmp_path: Path) -> None:
    require_core()
    src = polling_capture(tmp_path / "many.pcap", PAIRS)
    log = tmp_path / "x.mcap"
    bare = _faults([str(src), "-q"])
    logged = _faults([str(src), "-q", "-w", str(log)])
    assert log.stat().st_size > 1 << 20  # several blocks and chunks went through
    extra = logged - bare
    # the log's modules, its writer thread and a few blocks' first use: ~1,000 pages;
    # mapped and zeroed anew each time it would be ~11,000 here
    assert extra < 4_000, f"{extra} more page faults with the log ({bare} without)"
