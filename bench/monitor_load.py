"""What the interactive monitor costs at a given frame rate, on a real pseudo-terminal.

For each terminal size, a child process runs the monitor's screen (textual, its
real Linux driver writing escape sequences to a pty that this process reads and
throws away) over a :class:`~mbmon.monitor.feed.MonitorFeed` that a producer
thread feeds at ``--rate`` frames/s in batches every 10 ms, as the hub would.
The records are the project's HRSS capture (captures/hrss_ptp.pcap), repeated
with the times moved on, decoded before the clock starts.

Reported per size: the screen's CPU (the process's CPU minus the producer
thread's own, so: textual's loop, its writer thread, the copies and drawing) as
% of one core, redraws/s, and, from the producer, the feed listener's own cost
per record (what the hub's thread pays: counting, the register image, the
monitor line) as µs and as % of one core at the rate. Run:

    python bench/monitor_load.py                   # 5,000 frames/s, 10 s, 80x24 160x50 200x60
    python bench/monitor_load.py --rate 20000 --seconds 5
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import select
import struct
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _records(frames: int) -> list:
    """At least ``frames`` frame records: the HRSS capture again and again, times moved on."""
    from dataclasses import replace

    from mbmon.commands.common import make_annotator
    from mbmon.model import Chunk, Event
    from mbmon.pipeline import Pipeline
    from mbmon.sources.pcapfile import read_capture

    items = list(read_capture(REPO / "captures" / "hrss_ptp.pcap"))
    span = items[-1].ts - items[0].ts + 0.01
    pipeline = Pipeline(make_annotator(["hrss"]))
    out: list = []
    shift = 0.0
    while sum(r.frame is not None for r in out) < frames:
        for item in items:
            moved = replace(item, ts=item.ts + shift)
            assert isinstance(moved, (Chunk, Event))
            out.extend(pipeline.feed(moved))
        shift += span
    out.extend(pipeline.finish())
    return out


def child(fd: int, rate: int, seconds: float) -> None:
    """The screen on this process's terminal, fed at ``rate`` frames/s; figures to ``fd``."""
    from mbmon.format import View
    from mbmon.monitor.app import MonitorApp
    from mbmon.monitor.feed import MonitorFeed

    records = _records(int(rate * seconds) + 1000)
    feed = MonitorFeed(View(), title="mbmon bench", profile=True)
    stop = threading.Event()
    figures: dict[str, float] = {}

    def produce() -> None:
        t0 = time.thread_time()
        spent = 0.0
        frames = 0
        i = 0
        start = time.monotonic()
        while not stop.is_set() and i < len(records):
            due = start + frames / rate
            now = time.monotonic()
            if due > now:
                time.sleep(min(0.01, due - now))
                continue
            batch = []
            while i < len(records) and frames < (now - start + 0.01) * rate:
                batch.append(records[i])
                frames += records[i].frame is not None
                i += 1
            c0 = time.thread_time()
            feed.on_records(batch)
            spent += time.thread_time() - c0
        figures.update(producer_cpu=time.thread_time() - t0, feed_cpu=spent,
                       frames=frames, records=i)  # fmt: skip

    app = MonitorApp(feed)
    producer = threading.Thread(target=produce, daemon=True)

    def finish() -> None:
        stop.set()
        app.exit()

    cpu0 = time.process_time()
    wall0 = time.monotonic()
    producer.start()
    app.call_later(lambda: app.set_timer(seconds, finish))
    app.run()
    producer.join()
    wall = time.monotonic() - wall0
    cpu = time.process_time() - cpu0
    figures.update(wall=wall, cpu=cpu, redraws=app.redraws)
    with os.fdopen(fd, "w") as out:
        out.write(json.dumps(figures))


def run_size(columns: int, lines: int, rate: int, seconds: float) -> dict:
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", lines, columns, 0, 0))
    r, w = os.pipe()
    env = {**os.environ, "TERM": "xterm-256color", "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, __file__, "--child", str(w), "--rate", str(rate),
         "--seconds", str(seconds)],
        stdin=slave, stdout=slave, stderr=slave, pass_fds=(w,), env=env,
    )  # fmt: skip
    os.close(slave)
    os.close(w)
    shown = 0
    tail = b""
    while proc.poll() is None:
        if select.select([master], [], [], 0.2)[0]:
            try:
                data = os.read(master, 1 << 16)
            except OSError:
                break
            shown += len(data)
            tail = (tail + data)[-4000:]
    proc.wait()
    os.close(master)
    with os.fdopen(r) as f:
        text = f.read()
    figures = json.loads(text) if text else {"output": tail.decode("utf-8", "replace")}
    figures["terminal_bytes"] = shown
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", type=int, default=5000, help="frames/s (default 5000)")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--sizes", default="80x24,160x50,200x60")
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        child(args.child, args.rate, args.seconds)
        return
    print(f"monitor at {args.rate} frames/s for {args.seconds:g} s, on a real pty")
    print(f"{'size':>8} {'screen % core':>14} {'redraws/s':>10} {'feed µs/rec':>12} "
          f"{'feed % core':>12} {'frames/s fed':>13} {'tty KB/s':>9}")  # fmt: skip
    for size in args.sizes.split(","):
        cols, rows = (int(v) for v in size.split("x"))
        f = run_size(cols, rows, args.rate, args.seconds)
        if not f.get("wall"):
            print(f"{size:>8} failed:\n{f.get('output', '')}")
            continue
        wall = f["wall"]
        screen = (f["cpu"] - f["producer_cpu"]) / wall * 100
        per = f["feed_cpu"] / max(1, f["records"]) * 1e6
        print(f"{size:>8} {screen:>13.1f}% {f['redraws'] / wall:>10.1f} {per:>12.2f} "
              f"{f['feed_cpu'] / wall * 100:>11.1f}% {f['frames'] / wall:>13.0f} "
              f"{f['terminal_bytes'] / wall / 1024:>9.1f}")  # fmt: skip


if __name__ == "__main__":
    main()
