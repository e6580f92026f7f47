"""Highest lossless rate of ``mbmon sniff`` on loopback, on the compiled core and forced
pure (``MBMON_NO_EXTENSIONS=1``), next to tcpdump on the same traffic.

    sudo python bench/sniff_rate.py                       # 20k .. 300k ADU/s, 3 s each
    sudo python bench/sniff_rate.py --rates 5000 10000 --seconds 5 --paths pure
    python bench/sniff_rate.py --callgrind 20000          # instructions per ADU (hub side)

What this script owns: a bounded load generator and the figures. For each rate
(ADUs per second, requests + responses) it starts, as child processes,
``mbmon sniff lo --port P --json`` (stdout to /dev/null; its summary on stderr
gives frames seen and kernel drops) and ``tcpdump -i lo -w F 'tcp port P'``
(its summary gives packets captured and dropped by the kernel; the pcap is then
read back with ``mbmon read`` to count the ADUs tcpdump kept). The generator
is a raw Modbus/TCP server and one client on 127.0.0.1:P in this process: the
client sends Read Holding Registers requests (one per TCP segment, TCP_NODELAY)
paced per millisecond for ``--seconds``; the server answers each (15-byte
responses, coalesced per read; Linux's TCP autocorking also puts several
requests in one segment once the sender outruns the loopback device, so the
packets column says how many segments carried them). ADUs expected = 2 x requests answered. A rate
is lossless when sniff saw every ADU and the kernel dropped nothing. Needs root.

Before the rates, the generator runs alone, unpaced: the most it can put on the
wire on this machine (if a target rate is above it, the generator is the limit).
For each rate and path the sniff child's CPU time (user + sys, from the kernel's
accounting of the waited child) is given in all and per ADU: the machine is
shared, so CPU per ADU is the figure to compare, not wall time. A run without
traffic gives each path's fixed cost (start-up, ticks, the summary), taken off.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = Path(__file__).resolve().parent / "out"
TARGET = 100_000  # ADU/s, the live-capture target

REQUEST = bytes.fromhex("0000 0000 0006 01 03 0000 0003")
RESPONSE = bytes.fromhex("0000 0000 0009 01 03 06 0001 0002 0003")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _serve(listener: socket.socket, answered: list[int], stop: threading.Event) -> None:
    conn, _ = listener.accept()
    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    buf = b""
    with conn:
        while not stop.is_set():
            data = conn.recv(65536)
            if not data:
                return
            buf += data
            n = len(buf) // 12
            if n:
                out = []
                for i in range(n):
                    tid = buf[i * 12 : i * 12 + 2]
                    out.append(tid + RESPONSE[2:])
                buf = buf[n * 12 :]
                conn.sendall(b"".join(out))
                answered[0] += n


def generate(port: int, rate: int, seconds: float) -> int:
    """Send ``rate / 2`` requests per second for ``seconds`` (``rate`` 0: as fast as
    the loop goes); return ADUs on the wire."""
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", port))
    listener.listen()
    answered = [0]
    stop = threading.Event()
    server = threading.Thread(target=_serve, args=(listener, answered, stop), daemon=True)
    server.start()
    client = socket.create_connection(("127.0.0.1", port))
    client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def drain() -> None:
        while True:
            try:
                if not client.recv(65536):
                    return
            except OSError:
                return

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    per_second = rate / 2
    sent = 0
    t0 = time.perf_counter()
    end = t0 + seconds
    while True:
        now = time.perf_counter()
        if now >= end:
            break
        due = int((now - t0) * per_second) if rate else sent + 64
        while sent < due:
            tid = (sent + 1) & 0xFFFF
            client.send(tid.to_bytes(2) + REQUEST[2:])
            sent += 1
        if rate:
            time.sleep(0.0005)
    time.sleep(0.3)
    client.shutdown(socket.SHUT_WR)
    reader.join(timeout=2)
    client.close()
    stop.set()
    server.join(timeout=2)
    listener.close()
    return sent + answered[0]


def _ready(proc: subprocess.Popen[bytes], needle: bytes, timeout: float = 15) -> bytes:
    import select

    assert proc.stderr is not None
    got = b""
    end = time.monotonic() + timeout
    while needle not in got:
        if time.monotonic() > end or proc.poll() is not None:
            raise SystemExit(f"not ready: {got.decode(errors='replace')}")
        ready, _, _ = select.select([proc.stderr], [], [], 0.1)
        if ready:
            got += os.read(proc.stderr.fileno(), 4096)
    return got


def one_rate(
    rate: int, seconds: float, port: int, tcpdump: bool, path: str, as_json: bool
) -> dict[str, object]:
    OUT.mkdir(exist_ok=True)
    pcap = OUT / f"sniff_rate_{rate}.pcap"
    env = _env()
    env.pop("MBMON_NO_EXTENSIONS", None)
    if path == "pure":
        env["MBMON_NO_EXTENSIONS"] = "1"
    cmd = [sys.executable, "-m", "mbmon", "sniff", "lo", "--port", str(port)]
    sniff = subprocess.Popen(
        cmd + (["--json"] if as_json else []),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=env,
    )
    head = _ready(sniff, b"sniffing")
    dump = None
    if tcpdump:
        dump = subprocess.Popen(
            ["tcpdump", "-i", "lo", "-n", "-w", str(pcap), f"tcp port {port}"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        _ready(dump, b"listening")
    if rate < 0:  # no traffic: the run's fixed CPU cost (start, ticks, the summary)
        time.sleep(seconds + 0.3)
        wire = 0
    else:
        wire = generate(port, rate, seconds)
    time.sleep(1.0)
    sniff.send_signal(signal.SIGINT)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    _, err = sniff.communicate(timeout=300)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    text = (head + err).decode(errors="replace")
    frames = int(m.group(1)) if (m := re.search(r"(\d+) frames", text)) else -1
    drops = int(m.group(1)) if (m := re.search(r"(\d+) dropped", text)) else -1
    packets = int(m.group(1)) if (m := re.search(r"(\d+) packets captured", text)) else -1
    on_core = "core: the compiled core" in text
    handed = "then the Python pipeline" in text
    row: dict[str, object] = {
        "rate": rate,
        "wire": wire,
        "sniff": frames,
        "sniff_drops": drops,
        "cpu": cpu,
        "packets": packets,
        "ran": ("core+pure" if handed else "core") if on_core else "pure",
    }
    if dump is not None:
        dump.send_signal(signal.SIGINT)
        _, derr = dump.communicate(timeout=30)
        dtext = derr.decode(errors="replace")
        m = re.search(r"(\d+) packets dropped by kernel", dtext)
        row["tcpdump_drops"] = int(m.group(1)) if m else -1
        read = subprocess.run(
            [sys.executable, "-m", "mbmon", "read", str(pcap), "--port", str(port), "--json"],
            capture_output=True,
            env=_env(),
        )
        kinds = [json.loads(line)["kind"] for line in read.stdout.splitlines() if line.strip()]
        row["tcpdump"] = sum(1 for k in kinds if k in ("request", "response", "exception"))
    return row


_STREAM = """
import sys, io, os
from mbmon.io.pcap import TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response
n, mode = int(sys.argv[1]), sys.argv[2]
conv = TcpConversation("127.0.0.1:40000", "127.0.0.1:15020", linktype=1)
frames = conv.open()
for i in range(n // 2):
    tid = (i + 1) & 0xFFFF
    frames.append(conv.send(True, encode_adu(tid, 1, encode_read_request(3, 0, 3))))
    frames.append(conv.send(False, encode_adu(tid, 1, encode_read_response(3, [1, 2, 3]))))
frames += conv.close(True)
packets = [(1.7e9 + i * 1e-5, 1, f) for i, f in enumerate(frames)]
if mode == "gen":
    sys.exit(0)
from mbmon.format import View
from mbmon.hub import Hub
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.sinks.console import ConsoleListener
from mbmon.sources.pcapfile import CaptureConfig
from mbmon.sources.sniff import dissect_batch, open_dissector
from mbmon.timefmt import TimeFormat
out = open(os.devnull, "w")
view = View(time_format=TimeFormat("a"))
hub = Hub(Pipeline(None, PipelineConfig()))
hub.add_listener(ConsoleListener(out, view, as_json=True, live=True))
ports = frozenset({502, 15020})
dissector = open_dissector(CaptureConfig(tcp_ports=ports), hub.new_stream)
if mode == "core":
    from mbmon.core.live import LiveCore
    raw = out.buffer
    stage = LiveCore(ports=ports, timeout=1.0, view=view, as_json=True, write=raw.write,
                     flush=raw.flush, new_stream=hub.new_stream, dissector=dissector,
                     pipeline=hub.pipeline)
    feed = stage.packets
else:
    stage = dissector
    feed = lambda batch: dissect_batch(dissector, batch)
hub.add_ticker(stage)
for at in range(0, len(packets), 256):
    hub.feed_items(feed(packets[at:at + 256]))
hub.finish()
hub.close()
assert mode != "core" or stage.handed is None
"""


def _instructions(n: int, mode: str) -> int:
    out = OUT / "sniff-callgrind.out"
    env = _env()
    env.pop("MBMON_NO_EXTENSIONS", None)
    subprocess.run(
        ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", sys.executable, "-c",
         _STREAM, str(n), mode],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, check=True,
    )  # fmt: skip
    text = out.read_text(errors="replace")
    out.unlink()
    return int(next(ln for ln in text.splitlines() if ln.startswith("summary:")).split()[1])


def callgrind_figures(n: int) -> None:
    """Marginal instructions per ADU of the hub's side of ``sniff --json`` (the packets
    of a capture in batches of 256, one ADU per segment, through the core's stage or
    the reference dissector and pipeline, lines to /dev/null): (I(n) - I(n/5)) over
    the 4n/5 ADUs between, the packets' making (same in both) taken off."""
    OUT.mkdir(exist_ok=True)
    k = n - n % 10
    gen = _instructions(k, "gen") - _instructions(k // 5, "gen")
    for mode in ("core", "pure"):
        got = _instructions(k, mode) - _instructions(k // 5, mode) - gen
        print(f"callgrind instructions per ADU, {mode}: {got / (k - k // 5):,.0f}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--rates", type=int, nargs="+", default=[20000, 50000, 100000, 150000, 200000, 300000]
    )
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--port", type=int, default=15020)
    ap.add_argument("--no-tcpdump", action="store_true")
    ap.add_argument("--paths", nargs="+", choices=["core", "pure"], default=["core", "pure"])
    ap.add_argument("--text", action="store_true", help="sniff's text lines (default --json)")
    ap.add_argument("--callgrind", type=int, metavar="N", help="only: instructions per ADU")
    args = ap.parse_args()
    if args.callgrind:
        callgrind_figures(args.callgrind)
        return 0
    if os.geteuid() != 0:
        print("needs root (AF_PACKET capture)", file=sys.stderr)
        return 1
    alone = generate(args.port, 0, args.seconds)
    print(f"generator alone, unpaced: {int(alone / args.seconds)} ADU/s", flush=True)
    best = dict.fromkeys(args.paths, 0)
    met = dict.fromkeys(args.paths, False)
    idle = {}
    for path in args.paths:
        idle[path] = float(one_rate(-1, args.seconds, args.port, False, path, not args.text)["cpu"])  # type: ignore[arg-type]
        print(f"{path}: sniff without traffic for {args.seconds:g} s: {idle[path]:.2f} s CPU")
    print(
        f"{'path':>9} {'target':>8} {'achieved':>9} {'on wire':>9} {'sniff':>9} {'drops':>6} "
        f"{'packets':>8} {'CPU s':>6} {'us/ADU':>7} {'us/pkt':>7} {'tcpdump':>9} {'drops':>6}"
    )
    for rate in args.rates:
        for path in args.paths:
            row = one_rate(rate, args.seconds, args.port, not args.no_tcpdump, path, not args.text)
            lossless = row["sniff"] == row["wire"] and row["sniff_drops"] == 0
            wire = int(row["wire"])  # type: ignore[call-overload]
            achieved = int(wire / args.seconds)
            cpu = float(row["cpu"]) - idle[path]  # type: ignore[arg-type]
            if lossless:
                best[path] = max(best[path], achieved)
                met[path] = met[path] or rate >= TARGET
            print(
                f"{row['ran']:>9} {rate:>8} {achieved:>9} {wire:>9} {row['sniff']:>9} "
                f"{row['sniff_drops']:>6} {row['packets']:>8} {cpu:>6.2f} "
                f"{1e6 * cpu / max(wire, 1):>7.2f} "
                f"{1e6 * cpu / max(int(row['packets']), 1):>7.2f} "  # type: ignore[call-overload]
                f"{row.get('tcpdump', '-'):>9} {row.get('tcpdump_drops', '-'):>6}"
                f"  {'lossless' if lossless else 'LOST'}",
                flush=True,
            )
    for path, rate in best.items():
        print(
            f"highest lossless rate, {path}: {rate} ADU/s "
            f"(target {TARGET}: {'met' if met[path] else 'NOT met'})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
