"""The one pty-pair maker of the tests: two ends of a ``socat`` pty pair, where
what is written to one end is read on the other (a serial line without hardware).

Importable from any test (``pythonpath = ["tests"]`` in pyproject.toml); tests
that use it skip when socat is not installed.
"""

from __future__ import annotations

import re
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest


@contextmanager
def pty_pair() -> Iterator[tuple[str, str]]:
    """Two ends of a socat pty pair: what is written to one is read on the other."""
    proc = subprocess.Popen(
        ["socat", "-d", "-d", "pty,raw,echo=0", "pty,raw,echo=0"],
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    ptys: list[str] = []
    deadline = time.monotonic() + 10
    while len(ptys) < 2 and time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        m = re.search(r"PTY is (\S+)", line)
        if m:
            ptys.append(m.group(1))
    if len(ptys) < 2:
        proc.kill()
        pytest.fail("socat did not open a pty pair")
    threading.Thread(target=proc.stderr.read, daemon=True).start()
    try:
        yield ptys[0], ptys[1]
    finally:
        proc.terminate()
        proc.wait(timeout=5)
