"""TCP keepalive on the proxy's own sockets: a client or upstream whose host
vanished without a FIN or RST is noticed (the kernel's keepalive timer runs on
both sides of the proxy; read from /proc/net/tcp, where an idle connection's
timer field says 02 when keepalive is on and 00 when it is off)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from tests.proxy.test_proxy_e2e import connect, expected_hr, fake, proxy, read_hr, rpc

PROC_TCP = Path("/proc/net/tcp")


def _timers() -> list[tuple[int, int, str]]:
    """(local port, remote port, timer kind) of every established IPv4 socket."""
    out = []
    for line in PROC_TCP.read_text().splitlines()[1:]:
        fields = line.split()
        if fields[3] != "01":  # ESTABLISHED
            continue
        local = int(fields[1].split(":")[1], 16)
        remote = int(fields[2].split(":")[1], 16)
        out.append((local, remote, fields[5].split(":")[0]))
    return out


@pytest.mark.skipif(not PROC_TCP.exists(), reason="needs Linux's /proc/net/tcp")
def test_client_and_upstream_sockets_have_keepalive(tmp_path: Path) -> None:
    with fake() as up, proxy(up.port, "--quiet", tmp=tmp_path) as p:
        sock = connect(p.port)
        assert rpc(sock, 1, read_hr(0, 2)) == expected_hr(1, 1, 0, 2)
        client_port = sock.getsockname()[1]
        time.sleep(0.3)  # idle: no data in flight, so the timer shown is keepalive's
        timers = _timers()
        proxy_side = [t for (lp, rp, t) in timers if lp == p.port and rp == client_port]
        upstream_side = [t for (lp, rp, t) in timers if rp == up.port and lp != p.port]
        test_side = [t for (lp, rp, t) in timers if lp == client_port]
        sock.close()
    assert proxy_side == ["02"], timers  # the proxy's socket to the client
    assert upstream_side == ["02"], timers  # the proxy's socket to the upstream
    assert test_side == ["00"], timers  # the test's own socket: no keepalive, no timer
