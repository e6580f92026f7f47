"""The MCAP log's message volume: bytes per ADU and the CPU its chunks cost to compress
and checksum, for candidate layouts made from one log's own messages, in one run.

    python bench/log_volume.py LOG.mcap                  # an existing log (any format)
    python bench/log_volume.py --adus 200000             # write one from realistic.py's file

Each candidate rewrites every message of the log (same order, same heads) and
chunks the records as the writer does (about 1 MiB uncompressed per chunk);
then this process compresses each candidate's chunks with zstd at several levels
and takes their CRC-32, by CPU time (``time.process_time``), the same chunks for
every candidate. Candidates:

- ``format 1``: a format-1 log's messages as stored (a format-2 log's stay format 2, a
  format-3 log's are read as format 2's JSON: give this script a log written by the
  code before format 2 for that row);
- ``format 2``: ``/modbus/frames`` without ``line`` (the monitor message of the
  same record holds it) and without null members; ``/modbus/raw`` chunks without
  their null ``event``/``info``; ``/modbus/monitor`` with ``file`` empty;
- ``format 2, no endpoints``: also without ``src``/``dst``/``transport`` in frames
  and the endpoints in raw chunks (left in format 2: see docs/performance.md);
- ``format 2 without /modbus/monitor``: what that topic costs;
- format 3 candidates (``--format3``): ``/modbus/raw`` chunks and ``/modbus/frames`` in
  protobuf (data as bytes, values packed varints, kind an enum), ``full`` with the
  endpoints, the pdu and the notes, ``lean`` without them (the monitor line and the
  stream's events hold them), and the monitor line as today, without the time text and
  the endpoints its own fields show (``short``), or in protobuf.

``--per-topic`` also compresses each topic's messages on their own (not mixed in
chunks): what each topic costs by itself.

``--stored LOG...`` measures logs as they are instead (every message as stored, one
row a log): a format-3 and a format-4 log of the same capture, say, in the same run.

What this script owns: the measurement that chose format 2 (docs/performance.md,
"The log's message volume"). It reads the log with mbmon's reader.
"""

from __future__ import annotations

import argparse
import base64
import json
import re
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


def _varint(n: int) -> bytes:
    n &= (1 << 64) - 1
    out = bytearray()
    while n > 0x7F:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _pb_int(field: int, n: int | None) -> bytes:
    return b"" if n is None else _varint(field << 3) + _varint(n)


def _pb_bytes(field: int, data: bytes | str | None) -> bytes:
    if data is None:
        return b""
    if isinstance(data, str):
        data = data.encode()
    return _varint(field << 3 | 2) + _varint(len(data)) + data


def _pb_double(field: int, x: float | None) -> bytes:
    return b"" if x is None else _varint(field << 3 | 1) + struct.pack("<d", x)


_KINDS = {"request": 1, "response": 2, "exception": 3}


def _pb_raw(obj: dict) -> bytes:
    direction = {"c2s": 1, "s2c": 2}.get(obj.get("direction") or "", 0)
    return (
        _pb_int(1, obj["stream"]) + _pb_bytes(2, obj["client"]) + _pb_bytes(3, obj["server"])
        + _pb_int(4, direction) + _pb_double(5, obj["ts"])
        + _pb_bytes(6, base64.b64decode(obj["data"]))
    )  # fmt: skip


def _pb_frame(obj: dict, full: bool) -> bytes:
    values = obj.get("values")
    packed = b""
    if values:
        packed = b"".join(_varint(int(v)) for v in values)
        packed = _varint(12 << 3 | 2) + _varint(len(packed)) + packed
    out = (
        _pb_int(1, obj["index"]) + _pb_double(2, obj["time"]) + _pb_int(3, obj["stream"])
        + _pb_int(6, obj.get("tid")) + _pb_int(7, obj.get("unit")) + _pb_int(8, obj.get("fc"))
        + _pb_int(9, _KINDS.get(obj.get("kind", ""), 4)) + _pb_int(16, obj.get("exception_code"))
        + _pb_int(10, obj.get("address")) + _pb_int(11, obj.get("count")) + packed
        + _pb_double(15, obj.get("latency_ms")) + _pb_int(17, obj.get("request_index"))
    )  # fmt: skip
    if full:
        out += _pb_bytes(4, obj.get("src")) + _pb_bytes(5, obj.get("dst"))
        out += _pb_bytes(13, bytes.fromhex(obj.get("pdu") or ""))
        out += b"".join(_pb_bytes(14, n) for n in obj.get("notes") or ())
    return out


_PREFIX = re.compile(r"^\S+  (?:\S+ \S+ \S+  )?")


def _mon_short(raw: bytes) -> bytes:
    obj = json.loads(raw)
    obj["message"] = _PREFIX.sub("", obj["message"], count=1)
    return _dumps(obj)


def _mon_proto(raw: bytes) -> bytes:
    obj = json.loads(raw)
    stamp = _pb_int(1, obj["timestamp"]["sec"]) + _pb_int(2, obj["timestamp"]["nsec"])
    return (
        _pb_bytes(1, stamp) + _pb_int(2, obj["level"]) + _pb_bytes(3, obj["message"])
        + _pb_bytes(4, obj["name"]) + _pb_bytes(5, obj["file"]) + _pb_int(6, obj["line"])
    )  # fmt: skip


def _format3(full: bool, monitor: Callable[[bytes], bytes] | None) -> Candidate:
    def cand(topic: str, raw: bytes) -> bytes | None:
        data = _format2(topic, raw)
        if data is None:
            return None
        if topic == "/modbus/frames":
            return _pb_frame(json.loads(data), full)
        if topic == "/modbus/raw":
            obj = json.loads(data)
            return _pb_raw(obj) if obj.get("type") == "chunk" else data
        if topic == "/modbus/monitor" and monitor is not None:
            return monitor(data)
        return data

    return cand


FORMAT3: dict[str, Candidate] = {
    "3: raw, frames protobuf (full), monitor JSON": _format3(True, None),
    "3: raw, frames protobuf (lean), monitor JSON": _format3(False, None),
    "3: raw, frames protobuf (lean), monitor JSON short": _format3(False, _mon_short),
    "3: raw, frames protobuf (lean), monitor protobuf": _format3(False, _mon_proto),
}

CANDIDATES: dict[str, Candidate] = {
    "format 1": _format1,
    "format 2": _format2,
    "format 2, no endpoints in frames and raw": _format2_lean,
    "format 2 without /modbus/monitor": _no_monitor,
}


def _stored_json(msg: object) -> bytes:
    """A message's payload as JSON: a format-3 log's protobuf messages as the format-2
    objects they hold (so every candidate starts from format 2's JSON)."""
    if getattr(msg, "decoder", None) is None:
        return msg.raw  # type: ignore[attr-defined, no-any-return]
    return _dumps(msg.json())  # type: ignore[attr-defined]


def _as_stored(topic: str, raw: bytes) -> bytes | None:
    """The ``--stored`` candidate: a message as the log holds it (see :func:`_chunks`)."""
    return raw


def _chunks(log: Path, candidate: Candidate, per_topic: dict[str, int]) -> Iterator[bytes]:
    from mbmon.io.mcap.reader import McapLog

    parts: list[bytes] = []
    size = 0
    with McapLog(str(log)) as mlog:
        for msg in mlog.messages(None):
            stored = msg.raw if candidate is _as_stored else _stored_json(msg)
            data = candidate(msg.topic, stored)
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


def _per_topic(log: Path, candidate: Candidate, level: int) -> dict[str, tuple[int, float, int]]:
    """Each topic's messages concatenated and compressed on their own in 1 MiB pieces:
    topic -> (bytes, CPU seconds, compressed bytes)."""
    import zstandard

    from mbmon.io.mcap.reader import McapLog

    topics: dict[str, bytearray] = {}
    with McapLog(str(log)) as mlog:
        for msg in mlog.messages(None):
            data = candidate(msg.topic, _stored_json(msg))
            if data is not None:
                topics.setdefault(msg.topic, bytearray()).extend(data)
    comp = zstandard.ZstdCompressor(level=level)
    out: dict[str, tuple[int, float, int]] = {}
    for topic, buf in topics.items():
        data = bytes(buf)
        pieces = [data[i : i + CHUNK] for i in range(0, len(data), CHUNK)]
        t0 = time.process_time()
        packed = sum(len(comp.compress(p)) for p in pieces)
        out[topic] = (len(data), time.process_time() - t0, packed)
    return out


def measure(
    log: Path,
    adus: int,
    levels: list[int],
    candidates: dict[str, Candidate],
    per_topic: bool,
    logs: dict[str, Path] | None = None,
) -> None:
    """Print each candidate's bytes and CPU per 1M ADUs; ``logs``: a candidate's own log
    (``--stored``), else ``log``'s messages rewritten."""
    import zstandard

    fns: list[tuple[str, Callable[[bytes], object]]] = [
        (f"zstd {lv}", zstandard.ZstdCompressor(level=lv).compress) for lv in levels
    ]
    fns.append(("crc32", zlib.crc32))
    print(f"{log.name}, {adus:,} ADUs; CPU seconds per 1M ADUs in this process")
    for name, cand in candidates.items():
        topic_bytes: dict[str, int] = {}
        chunks = list(_chunks((logs or {}).get(name, log), cand, topic_bytes))
        total = sum(len(c) for c in chunks)
        cost: dict[str, float] = {}
        packed: dict[str, int] = {}
        for label, fn in fns:
            t0 = time.process_time()
            outs = [fn(c) for c in chunks]
            cost[label] = time.process_time() - t0
            if label != "crc32":
                packed[label] = sum(len(o) for o in outs)  # type: ignore[arg-type]
        topics = ", ".join(f"{t} {b / adus:,.0f}" for t, b in topic_bytes.items())
        print(f"  {name}: {total / adus:,.0f} bytes per ADU ({topics})")
        for label, sec in cost.items():
            extra = (
                f", {packed[label] / adus:,.0f} bytes per ADU compressed" if label in packed else ""
            )
            print(f"    {label}: {sec * 1e6 / adus:.2f} s{extra}")
        if per_topic:
            for topic, (size, sec, packed_size) in _per_topic(log, cand, levels[-1]).items():
                print(
                    f"    alone, zstd {levels[-1]}: {topic} {size / adus:,.0f} bytes per ADU,"
                    f" {sec * 1e6 / adus:.2f} s, {packed_size / adus:,.0f} compressed"
                )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", nargs="?", help="an MCAP log (default: write one)")
    ap.add_argument("--adus", type=int, default=200_000, help="ADUs of the file to write")
    ap.add_argument(
        "--levels", default="3,2,1,-1,-3,-5", help="zstd levels (the last: --per-topic's)"
    )
    ap.add_argument(
        "--format3", action="store_true", help="format 2 and the format 3 candidates only"
    )
    ap.add_argument("--per-topic", action="store_true", help="also each topic compressed alone")
    ap.add_argument("--stored", nargs="+", metavar="LOG", help="these logs as stored, one row each")
    args = ap.parse_args(argv)
    if args.stored:
        from mbmon.io.mcap.reader import McapLog

        logs = {f"{p} (format {McapLog(p).metadata['mbmon'].get('format')})": Path(p)
                for p in args.stored}  # fmt: skip
        with McapLog(args.stored[0]) as mlog:
            adus = sum(1 for m in mlog.messages(["/modbus/frames"]))
        levels = [int(x) for x in args.levels.split(",")]
        measure(Path(args.stored[0]), adus, levels, dict.fromkeys(logs, _as_stored), False, logs)
        return 0
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
    candidates = CANDIDATES
    if args.format3:
        candidates = {"format 2": _format2, **FORMAT3}
    measure(log, adus, [int(x) for x in args.levels.split(",")], candidates, args.per_topic)
    return 0


if __name__ == "__main__":
    sys.exit(main())
