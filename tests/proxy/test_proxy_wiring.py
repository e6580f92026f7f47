"""``mbmon proxy`` ends and outputs through the commands' one API: its outputs are
attached in the one order (logs, then the screen), a signal is its normal end
(exit 0) and an output that failed makes it 1."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.proxy.test_proxy_e2e import connect, fake, proxy, read_hr, rpc


def test_a_log_that_fails_makes_the_run_end_with_status_1(tmp_path: Path) -> None:
    """The exit status is :func:`exit_status`'s: an output that failed is 1 even
    though a signal (the proxy's normal end) stopped the run; the records that
    reached it are said lost on stderr, and the proxy forwarded on regardless."""
    full = Path("/dev/full")
    if not full.exists():
        pytest.skip("/dev/full is not there: no file that fails every write")
    (tmp_path / "t.jsonl").symlink_to(full)
    with fake() as up, proxy(up.port, "--quiet", "-w", "t.jsonl", tmp=tmp_path) as p:
        sock = connect(p.port)
        for tid in range(1, 200):
            assert rpc(sock, tid, read_hr(0, 2))[7] == 3
        sock.close()
        time.sleep(0.3)
        _out, err = p.stop()
    assert p.returncode == 1, err
    assert "mbmon: t.jsonl: " in err and "Traceback" not in err


def test_a_signal_ends_the_proxy_with_status_0_and_its_summary(tmp_path: Path) -> None:
    with fake() as up, proxy(up.port, "--quiet", tmp=tmp_path) as p:
        sock = connect(p.port)
        assert rpc(sock, 1, read_hr(0, 1))[7] == 3
        sock.close()
        _out, err = p.stop()
    assert p.returncode == 0, err
    assert "mbmon proxy: " in err and "Traceback" not in err
