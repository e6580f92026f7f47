"""The MCAP log's message volume: bytes per ADU and the CPU its chunks cost to compress
and checksum, for candidate layouts made from one log's own messages, in one run.

    python bench/log_volume.py LOG.mcap                  # an existing log (any format)
    python bench/log_volume.py --adus 200000             # write one from realistic.py's file

Each candidate rewrites every message of the log (same order, same heads) and
chunks the records as the writer does (about 1 MiB uncompressed per chunk);
then this process compresses each candidate's chunks with zstd at several levels
and takes their CRC-32, by CPU time (``time.process_time``), the same chunks for
every candidate. Candidates:

- ``format 1``: a format-1 log's messages (a format-2 log's are made format 1 first:
  give this script a log written by the code before format 2 for that row);
- ``format 2``: ``/modbus/frames`` without ``line`` (the monitor message of the
  same record holds it) and without null members; ``/modbus/raw`` chunks without
  their null ``event``/``info``; ``/modbus/monitor`` with ``file`` empty;
- ``format 2, no endpoints``: also without ``src``/``dst``/``transport`` in frames
  and the endpoints in raw chunks (left in format 2: see docs/performance.md);
- ``format 2 without /modbus/monitor``: what that topic costs.

What this script owns: the measurement that chose format 2 (docs/performance.md,
"The log's message volume"). It reads the log with mbmon's reader.
"""

from __future__ import annotations

import argparse
import json
import struct
import subprocess
import sys
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO))

HEAD = struct.Struct("<BQHIQQ")  # opcode, length, channel, sequence, log time, publish time
CHUNK = 1 << 20


def _dumps(obj: dict) -> bytes:
    return json.dumps(obj, separators=(",", ":"), ensure_ascii=False).encode()


Candidate = Callable[[str, bytes], bytes | None]


def _format1(topic: str, raw: bytes) -> bytes | None:
    return raw


def _format2(topic: str, raw: bytes) -> bytes | None:
    """Format 2 (what the writers now make): frames without line and null members, raw
    chunks without their null event/info, the monitor's file empty."""
    if topic == "/modbus/frames":
        obj = json.loads(raw)
        return _dumps({k: v for k, v in obj.items() if v is not None and k != "line"})
    if topic == "/modbus/raw":
        obj = json.loads(raw)
        if obj.get("type") == "chunk":
            obj.pop("event", None)
            obj.pop("info", None)
        return _dumps(obj)
    if topic == "/modbus/monitor":
        return _dumps({**json.loads(raw), "file": ""})
    return raw


def _format2_lean(topic: str, raw: bytes) -> bytes | None:
    """Format 2, and what it keeps for robustness or readers left out too: frames without
    src/dst/transport (the stream's), raw chunks without their endpoints."""
    data = _format2(topic, raw)
    if data is None or topic not in ("/modbus/frames", "/modbus/raw"):
        return data
    obj = json.loads(data)
    for key in ("src", "dst", "transport", "client", "server"):
        obj.pop(key, None)
    return _dumps(obj)


def _no_monitor(topic: str, raw: bytes) -> bytes | None:
    return None if topic == "/modbus/monitor" else _format2(topic, raw)


CANDIDATES: dict[str, Candidate] = {
    "format 1": _format1,
    "format 2": _format2,
    "format 2, no endpoints in frames and raw": _format2_lean,
    "format 2 without /modbus/monitor": _no_monitor,
}


def _chunks(log: Path, candidate: Candidate, per_topic: dict[str, int]) -> Iterator[bytes]:
    from mbmon.io.mcap.reader import McapLog

    parts: list[bytes] = []
    size = 0
    with McapLog(str(log)) as mlog:
        for msg in mlog.messages(None):
            data = candidate(msg.topic, msg.raw)
            if data is None:
                continue
            rec = HEAD.pack(5, 22 + len(data), 1, 0, msg.log_time, msg.publish_time) + data
            per_topic[msg.topic] = per_topic.get(msg.topic, 0) + len(rec)
            parts.append(rec)
            size += len(rec)
            if size >= CHUNK:
                yield b"".join(parts)
                parts, size = [], 0
    if parts:
        yield b"".join(parts)


def measure(log: Path, adus: int, levels: list[int]) -> None:
    import zstandard

    fns: list[tuple[str, Callable[[bytes], object]]] = [
        (f"zstd {lv}", zstandard.ZstdCompressor(level=lv).compress) for lv in levels
    ]
    fns.append(("crc32", zlib.crc32))
    print(f"{log.name}, {adus:,} ADUs; CPU seconds per 1M ADUs in this process")
    for name, cand in CANDIDATES.items():
        per_topic: dict[str, int] = {}
        chunks = list(_chunks(log, cand, per_topic))
        total = sum(len(c) for c in chunks)
        cost: dict[str, float] = {}
        packed: dict[str, int] = {}
        for label, fn in fns:
            t0 = time.process_time()
            outs = [fn(c) for c in chunks]
            cost[label] = time.process_time() - t0
            if label != "crc32":
                packed[label] = sum(len(o) for o in outs)  # type: ignore[arg-type]
        topics = ", ".join(f"{t} {b / adus:,.0f}" for t, b in per_topic.items())
        print(f"  {name}: {total / adus:,.0f} bytes per ADU ({topics})")
        for label, sec in cost.items():
            extra = (
                f", {packed[label] / adus:,.0f} bytes per ADU compressed" if label in packed else ""
            )
            print(f"    {label}: {sec * 1e6 / adus:.2f} s{extra}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", nargs="?", help="an MCAP log (default: write one)")
    ap.add_argument("--adus", type=int, default=200_000, help="ADUs of the file to write")
    ap.add_argument("--levels", default="3,2,1,-1,-3,-5", help="zstd levels")
    args = ap.parse_args(argv)
    if args.log:
        log = Path(args.log)
        from mbmon.io.mcap.reader import McapLog

        with McapLog(str(log)) as mlog:
            adus = sum(1 for m in mlog.messages(["/modbus/frames"]))
    else:
        from realistic import OUT, capture

        src = capture("polling", args.adus, 8, 2, "aligned")
        log = OUT / "log-volume.mcap"
        subprocess.run(
            [sys.executable, "-m", "mbmon", "read", str(src), "-q", "-w", str(log)],
            cwd=REPO, check=True,
        )  # fmt: skip
        adus = args.adus
    measure(log, adus, [int(x) for x in args.levels.split(",")])
    return 0


if __name__ == "__main__":
    sys.exit(main())
