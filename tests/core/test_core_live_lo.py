"""``mbmon sniff lo`` on the compiled core against the same command forced pure
(``MBMON_NO_EXTENSIONS=1``), capturing the same traffic at the same time: stdout byte
for byte, text and JSON. The traffic (raw sockets on 127.0.0.1, in this process):
handshakes, ADUs split across segments and several in one, exceptions, a FIN close,
a RST close, a connection that sends noise, and last one over IPv6 (::1) with noise
and an MBAP length of 255 in it: the core keeps the whole run (no hand-over to the
Python pipeline). Needs root (an AF_PACKET socket); CI runs as root."""

from __future__ import annotations

import json
import os
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

import pytest
from core_diff import require_core

from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_exception, encode_read_request, encode_read_response

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() != 0,
    reason="live capture needs root (an AF_PACKET socket); CI runs as root",
)


def _env(pure: bool) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("MBMON_NO_EXTENSIONS", None)
    if pure:
        env["MBMON_NO_EXTENSIONS"] = "1"
    return env


def _sniffer(port: int, as_json: bool, pure: bool) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", "mbmon", "sniff", "lo", "--port", str(port), "--debug-core"]
    cmd += ["--json"] if as_json else []
    return subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(pure), cwd=REPO
    )


def _wait_ready(proc: subprocess.Popen[bytes], timeout: float = 60.0) -> bytes:
    assert proc.stderr is not None
    got = b""
    end = time.monotonic() + timeout
    while b"sniffing" not in got:
        if time.monotonic() > end or proc.poll() is not None:
            raise AssertionError(f"sniff did not start: {got.decode(errors='replace')}")
        ready, _, _ = select.select([proc.stderr], [], [], 0.1)
        if ready:
            got += os.read(proc.stderr.fileno(), 4096)
    return got


def _server(listener: socket.socket, stop: threading.Event) -> None:
    """Answer every whole request ADU of each connection (read holding registers:
    its count of values; anything else: exception 01); noise is skipped."""

    def serve(conn: socket.socket) -> None:
        buf = b""
        with conn:
            while True:
                try:
                    data = conn.recv(65536)
                except OSError:
                    return
                if not data:
                    return
                buf += data
                out = b""
                while len(buf) >= 8:
                    if buf[2:4] != b"\0\0":
                        buf = b""  # noise: dropped
                        break
                    length = struct.unpack(">H", buf[4:6])[0]
                    if len(buf) < 6 + length:
                        break
                    adu, buf = buf[: 6 + length], buf[6 + length :]
                    tid, unit, fc = adu[0:2], adu[6], adu[7]
                    if fc == 3:
                        count = struct.unpack(">H", adu[10:12])[0]
                        pdu = encode_read_response(3, list(range(count)))
                    else:
                        pdu = encode_exception(fc, 1)
                    out += encode_adu(int.from_bytes(tid), unit, pdu)
                if out:
                    conn.sendall(out)

    listener.settimeout(0.2)
    while not stop.is_set():
        try:
            conn, _ = listener.accept()
        except TimeoutError:
            continue
        except OSError:
            return
        threading.Thread(target=serve, args=(conn,), daemon=True).start()


def _client(port: int, host: str = "127.0.0.1") -> socket.socket:
    sock = socket.create_connection((host, port))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def _drain(sock: socket.socket, expect: int) -> None:
    got = 0
    sock.settimeout(5)
    while got < expect:
        data = sock.recv(65536)
        if not data:
            return
        got += len(data)


def _traffic(port: int, ipv6: bool) -> None:
    pause = 0.02
    # a FIN close: single ADUs, split ADUs, several in one segment, an exception
    a = _client(port)
    sent = 0
    for tid in range(1, 21):
        adu = encode_adu(tid, 1, encode_read_request(3, tid, 1 + tid % 5))
        if tid % 4 == 1:  # split inside the header and the PDU
            a.sendall(adu[:3])
            time.sleep(pause)
            a.sendall(adu[3:9])
            time.sleep(pause)
            a.sendall(adu[9:])
        else:
            a.sendall(adu)
        sent += 9 + 2 * (1 + tid % 5)
        time.sleep(pause)
    a.sendall(b"".join(encode_adu(100 + i, 1, encode_read_request(3, i, 2)) for i in range(5)))
    sent += 5 * 13
    a.sendall(encode_adu(200, 1, encode_read_request(4, 0, 2)))  # answered with an exception
    sent += 9
    _drain(a, sent)
    a.shutdown(socket.SHUT_WR)
    time.sleep(0.2)
    a.close()
    # a RST close
    b = _client(port)
    b.sendall(encode_adu(1, 7, encode_read_request(3, 0, 3)))
    _drain(b, 15)
    b.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    b.close()
    time.sleep(0.2)
    # noise (the core's reference decoder settles it at the hub's tick); then more
    # requests on a new connection
    c = _client(port)
    c.sendall(encode_adu(1, 3, encode_read_request(3, 0, 1)))
    _drain(c, 11)
    c.sendall(b"\x01\x02 this is no MBAP header \x03")
    time.sleep(2.0)  # the noise is settled by the hub's ticks before anything else
    d = _client(port)
    for tid in range(1, 6):
        d.sendall(encode_adu(tid, 4, encode_read_request(3, tid, 2)))
        time.sleep(pause)
    _drain(d, 5 * 13)
    d.close()
    c.close()
    time.sleep(0.5)
    if ipv6:  # over IPv6: requests, noise, a length-255 ADU, requests again
        e = _client(port, "::1")
        e.sendall(encode_adu(1, 5, encode_read_request(3, 0, 2)))
        _drain(e, 13)
        e.sendall(b"\xff\xfe noise \x00")
        time.sleep(2.0)
        e.sendall(bytes((0, 9, 0, 0, 0, 255, 1, 0x5A)) + bytes(253))
        time.sleep(2.0)
        for tid in range(10, 14):
            e.sendall(encode_adu(tid, 5, encode_read_request(3, tid, 1)))
            time.sleep(pause)
        e.close()
        time.sleep(0.5)


def test_sniff_lo_on_the_core_equals_pure() -> None:
    require_core()
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = int(probe.getsockname()[1])
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", port))
    listener.listen()
    stop = threading.Event()
    server = threading.Thread(target=_server, args=(listener, stop), daemon=True)
    server.start()
    listener6 = None
    if socket.has_ipv6:
        try:
            listener6 = socket.socket(socket.AF_INET6)
            listener6.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            listener6.bind(("::1", port))
            listener6.listen()
        except OSError:  # no ::1 on this machine's loopback
            listener6 = None
        else:
            threading.Thread(target=_server, args=(listener6, stop), daemon=True).start()
    procs = {
        (as_json, pure): _sniffer(port, as_json, pure)
        for as_json in (False, True)
        for pure in (False, True)
    }
    heads = {}
    try:
        for key, proc in procs.items():
            heads[key] = _wait_ready(proc)
        _traffic(port, listener6 is not None)
        time.sleep(1.0)
        results = {}
        for proc in procs.values():
            proc.send_signal(signal.SIGINT)
        for key, proc in procs.items():
            out, err = proc.communicate(timeout=120)
            results[key] = (out, (heads[key] + err).decode(errors="replace"))
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
        stop.set()
        listener.close()
        if listener6 is not None:
            listener6.close()
    for as_json in (False, True):
        core_out, core_err = results[(as_json, False)]
        pure_out, pure_err = results[(as_json, True)]
        assert "core: the compiled core runs the capture" in core_err, core_err
        assert "MBMON_NO_EXTENSIONS" in pure_err, pure_err
        # noise, length 255 and IPv6 stayed on the core
        assert "then the Python pipeline" not in core_err, core_err
        assert core_out.count(b"\n") > 60
        assert _untimed(core_out, as_json) == _untimed(pure_out, as_json), (core_err, pure_err)


_TIME = re.compile(rb"\d\d:\d\d:\d\d\.\d{6}")
_LATENCY = re.compile(rb"\(\d+\.\d ms\)")


def _untimed(out: bytes, as_json: bool) -> list[object]:
    """The lines without their times: two packet sockets get the same packet with
    timestamps microseconds apart, so the times (and latencies) of two sniffers
    differ; everything else must not."""
    lines: list[object] = []
    for line in out.splitlines():
        line = _LATENCY.sub(b"(L)", _TIME.sub(b"T", line))
        if as_json:
            record = json.loads(line)
            record.pop("time", None)
            record.pop("latency_ms", None)
            lines.append(record)
        else:
            lines.append(line)
    return lines
