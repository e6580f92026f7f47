"""``mbmon proxy`` is wiring around its source (sources/proxy.ProxySource): the proxy
listens before any output is opened, so one that cannot listen says why in one line,
exits 1 and leaves no log or other file behind (as ``sniff`` and ``read`` do)."""

from __future__ import annotations

import socket
from pathlib import Path

from mbmon_cli import mbmon


def test_a_proxy_that_cannot_listen_leaves_no_log_behind(tmp_path: Path) -> None:
    log, lines = tmp_path / "p.mcap", tmp_path / "p.jsonl"
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = mbmon(
            "proxy",
            "--upstream",
            "127.0.0.1:1",
            "--listen",
            f"127.0.0.1:{port}",
            "-w",
            log,
            "-w",
            lines,
            timeout=60,
        )
    assert done.returncode == 1, done.stderr
    assert f"cannot listen on 127.0.0.1:{port}" in done.stderr
    assert "Traceback" not in done.stderr
    assert not log.exists() and not lines.exists()
    assert list(tmp_path.iterdir()) == []
