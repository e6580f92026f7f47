"""The proxy's screen: the interactive monitor shows proxied traffic and the proxy's own
figures; ``--plain`` (or no terminal) gives plain monitor lines.

Real parts: the HRSS simulator on 127.0.0.1 as the upstream, the proxy engine on
its own thread, the hub and the monitor's feed drawn by the textual screen headless;
the command itself on a real pseudo-terminal for the screen choice.
"""

from __future__ import annotations

import os
import pty
import re
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

from mbmon.commands.common import Figures
from mbmon.format import View
from mbmon.hub import Hub
from mbmon.monitor.app import render_text
from mbmon.monitor.feed import MonitorFeed
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.proxy.config import ProxyConfig, endpoint
from mbmon.proxy.engine import ProxyEngine
from mbmon.proxy.guard import Guard
from mbmon.proxy.observer import Observer
from mbmon.proxy.runner import ProxyThread
from mbmon.sim.server import SimServer

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def _adu(tid: int, pdu: bytes, unit: int = 1) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def _rpc(sock: socket.socket, tid: int, pdu: bytes) -> bytes:
    sock.sendall(_adu(tid, pdu))
    buf = b""
    while len(buf) < 7 or len(buf) < 6 + struct.unpack(">H", buf[4:6])[0]:
        part = sock.recv(300)
        assert part, "proxy closed the connection"
        buf += part
    return buf


def test_live_monitor_renders_proxied_traffic_and_proxy_figures() -> None:
    with SimServer() as sim:
        host, port = sim.host, sim.port
        upstream = endpoint(host, port)
        view = View(robot=upstream)
        monitor = MonitorFeed(view, title="mbmon proxy test")
        hub = Hub(Pipeline(None, PipelineConfig(timeout=4.0)))
        hub.add_listener(monitor)
        config = ProxyConfig(
            upstream_host=host,
            upstream_port=port,
            listen_port=0,
            guard=Guard.from_options(True, [], [], 1),
        )
        engine = ProxyEngine(config, Observer(hub.put, hub.new_stream), submit=hub.submit)
        hub.add_listener(Figures(monitor, engine.figures))
        thread = ProxyThread(engine, on_exit=hub.stop)
        _, lport = thread.start()
        runner = threading.Thread(target=hub.run, daemon=True)
        runner.start()
        try:
            with socket.create_connection(("127.0.0.1", lport), timeout=5) as s:
                read = _rpc(s, 7, struct.pack(">BHH", 3, 0, 4))
                assert read[7:9] == b"\x03\x08"
                refused = _rpc(s, 8, struct.pack(">BHH", 6, 200, 5))
                assert refused[7:] == b"\x86\x01"
                time.sleep(0.3)  # a tick of the hub: the figures reach the monitor
                seen = engine.figures()
                assert seen["clients"] == 1 and seen["upstream"] == "up"
        finally:
            thread.stop()
            thread.join(5)
            runner.join(5)
            hub.close()
        monitor.on_tick(time.time())
        text = render_text(monitor, (300, 60))
    # both directions with the robot's (the upstream's) labels; the refused write and
    # the guard's answer between the client and the proxy (never the robot), paired
    assert re.search(r"Receive from client  \[u1 t7\]  03 00 00 00 04 ", text), text
    assert re.search(r"Send to client  \[u1 t7\]  03 08( [0-9A-F]{2}){8} ", text), text
    proxy_at = re.escape(f"127.0.0.1:{lport}")
    client_at = r"127\.0\.0\.1:\d+"
    assert re.search(rf"{client_at} → {proxy_at}  \[u1 t8\]  06 00 C8 00 05 ", text), text
    assert re.search(rf"{proxy_at} → {client_at}  \[u1 t8\]  86 01  \| .*\(\d+\.\d ms\)", text)
    assert "Receive from client  [u1 t8]" not in text
    assert "Send to client  [u1 t8]" not in text
    assert "No response" not in text
    assert "Guard: refused 0x06 write R200 on unit 1 (read-only)" in text
    # the proxy's own figures in the header
    assert "guard refusals 1" in text
    assert "upstream up" in text
    assert "0x0A answers 0" in text and "0x0B answers 0" in text
    assert "requests 2" in text and "responses 1" in text and "exceptions 1" in text


def _run_on_a_terminal(args: list[str], upstream: int) -> str:
    """``mbmon proxy ARGS`` with stdout on a pseudo-terminal; one request through it;
    what the terminal showed."""
    master, slave = pty.openpty()
    os.set_blocking(master, False)
    command = ["proxy", "--upstream", f"127.0.0.1:{upstream}", "--listen", "127.0.0.1:0"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", *command, *args],
        stdin=slave,  # the screen reads its keys there
        stdout=slave,
        stderr=subprocess.PIPE,
        text=True,
        env={**ENV, "COLUMNS": "200", "LINES": "40", "TERM": "xterm"},
    )
    os.close(slave)
    shown = b""
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()
        m = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
        assert m, line
        with socket.create_connection(("127.0.0.1", int(m.group(1))), timeout=5) as s:
            _rpc(s, 1, struct.pack(">BHH", 3, 0, 2))
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            if select.select([master], [], [], 0.1)[0]:
                try:
                    shown += os.read(master, 65536)
                except OSError:
                    break
            if b"Send to client" in shown and time.monotonic() > deadline - 2:
                break
    finally:
        proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 20  # read on while it closes: a full pty would block it
        try:
            while proc.poll() is None and time.monotonic() < deadline:
                if select.select([master], [], [], 0.2)[0]:
                    part = os.read(master, 65536)
                    if not part:
                        break
                    shown += part
        except OSError:
            pass
        proc.wait(5)
        os.close(master)
    return shown.decode("utf-8", "replace")


def test_terminal_gets_live_screen_and_plain_gives_lines() -> None:
    with SimServer() as sim:
        live = _run_on_a_terminal([], sim.port)
        plain = _run_on_a_terminal(["--plain"], sim.port)
    # the live screen: the monitor panel and the proxy's figures, drawn with escapes
    assert "monitor" in live and "guard refusals" in live and "\x1b[" in live, live[-2000:]
    assert re.search(r"Send to client  \[u1 t1\]  03 04", live)
    # --plain on the same terminal: plain monitor lines, no screen
    assert "guard refusals" not in plain and "╭" not in plain, plain
    assert re.search(r"^\S.*Receive from client  \[u1 t1\]  03 00 00 00 02", plain, re.M), plain
    assert re.search(r"Send to client  \[u1 t1\]  03 04", plain)
