"""Throughput of ``mbmon read --json`` against tshark on one large Modbus/TCP capture.

    python bench/read_throughput.py                    # 1,000,000 ADUs, mbmon and tshark
    python bench/read_throughput.py --adus 250000 --skip-tshark
    python bench/read_throughput.py --flat             # also mbmon on N/4 ADUs: RSS flat in size?
    python bench/read_throughput.py --mcap             # also -w x.mcap vs -w x.jsonl
    python bench/read_throughput.py --profile 100000   # cProfile of mbmon read on 100k ADUs

What this script owns: the synthetic capture (built once, cached in
``bench/out/``), running each command as its own child process, and the
figures: wall time, ADUs/s and peak RSS of that child (``os.wait4`` rusage, so
every figure belongs to exactly one process), the mbmon/tshark ratio and the
targets (>= 5x tshark's ADUs/s, peak RSS < 150 MB, flat in size).

The capture: Ethernet/IPv4/TCP, server 10.0.0.1:502, 16 client connections
(each opened with a three-way handshake, closed with FIN), transactions
interleaved at random across connections, function codes 01 02 03 04 05 06 0F
10 with about 2 % exception answers (codes 01-04); about 10 % of the
transactions are pipelined (2-4 requests in one segment, their responses
coalesced in one segment) and about 4 % of the ADUs are split over two
segments. By default the cut falls after the MBAP header and function code
(byte 8 or later): tshark cannot reassemble an ADU whose first segment holds
fewer than 8 bytes and then loses the rest of that TCP direction (every later
segment becomes "TCP segment of a reassembled PDU"), which would make it skip
work and the comparison meaningless. ``--split-anywhere`` cuts anywhere,
including inside the 7-byte header (mbmon must still decode every ADU; tshark
then reports fewer). No bare ACKs, no checksums (neither tool checks them).
Deterministic (seeded).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import random
import shutil
import struct
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# The children run mbmon as an install runs it: from compiled bytecode. A shell that sets
# PYTHONDONTWRITEBYTECODE (this development machine's does) would have every child compile
# the sources it imports again (about 0.13 s a run); without it the first run writes the
# .pyc files and every later one reads them, as after `pip install`. tshark has no such cost.
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
OUT = REPO / "bench" / "out"
GEN_VERSION = 1  # bump when the generator changes: the cache key

sys.path.insert(0, str(REPO))
from mbmon.protocol.pdu import (  # noqa: E402
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
)

TARGET_RATIO = 5.0
TARGET_RSS_MB = 150.0

# --------------------------------------------------------------------------- capture builder

SERVER_IP = bytes((10, 0, 0, 1))
SERVER_PORT = 502
N_CONN = 16
FC_WEIGHTS = {0x01: 8, 0x02: 8, 0x03: 30, 0x04: 30, 0x05: 6, 0x06: 8, 0x0F: 4, 0x10: 6}
P_EXCEPTION = 0.02
P_PIPELINE = 0.10  # of the steps
P_SPLIT = 0.04  # of the ADUs in single-transaction steps
VARIANTS = 32  # templates per function code


def _templates(rng: random.Random) -> dict[int, list[tuple[bytes, bytes]]]:
    """(request PDU, normal response PDU) variants per function code (project encoders)."""
    out: dict[int, list[tuple[bytes, bytes]]] = {}
    for fc in FC_WEIGHTS:
        pairs = []
        for _ in range(VARIANTS):
            addr = rng.randrange(0, 60000)
            if fc in (0x01, 0x02):
                n = rng.randrange(1, 200)
                bits = [rng.randrange(2) for _ in range(n)]
                pairs.append((encode_read_request(fc, addr, n), encode_read_response(fc, bits)))
            elif fc in (0x03, 0x04):
                n = rng.randrange(1, 126)
                regs = [rng.randrange(65536) for _ in range(n)]
                pairs.append((encode_read_request(fc, addr, n), encode_read_response(fc, regs)))
            elif fc == 0x05:
                p = encode_write_single(fc, addr, rng.random() < 0.5)
                pairs.append((p, p))
            elif fc == 0x06:
                p = encode_write_single(fc, addr, rng.randrange(65536))
                pairs.append((p, p))
            else:
                n = rng.randrange(1, 60 if fc == 0x10 else 400)
                vals = [rng.randrange(65536 if fc == 0x10 else 2) for _ in range(n)]
                pairs.append(
                    (
                        encode_write_multiple_request(fc, addr, vals),
                        encode_write_multiple_response(fc, addr, n),
                    )
                )
        out[fc] = pairs
    return out


@dataclass
class _Conn:
    """One client connection: addresses, sequence numbers, next transaction id."""

    ip: bytes
    port: int
    cseq: int
    sseq: int
    tid: int = 0
    unit: int = 1


class _Writer:
    """Classic pcap, Ethernet/IPv4/TCP frames packed with struct (no checksums)."""

    ETH_C2S = b"\x02\x00\x00\x00\x00\x01" + b"\x02\x00\x00\x00\x00\x02" + b"\x08\x00"
    ETH_S2C = b"\x02\x00\x00\x00\x00\x02" + b"\x02\x00\x00\x00\x00\x01" + b"\x08\x00"

    def __init__(self, f: io.BufferedWriter) -> None:
        self.f = f
        self.buf = bytearray()
        self.ts_us = 1_700_000_000 * 1_000_000
        self.ip_id = 0
        self.packets = 0
        f.write(struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 262144, 1))

    def seg(self, c: _Conn, c2s: bool, payload: bytes, flags: int = 0x18) -> None:
        self.ts_us += 97
        self.ip_id = (self.ip_id + 1) & 0xFFFF
        if c2s:
            eth, src, dst, sp, dp = self.ETH_C2S, c.ip, SERVER_IP, c.port, SERVER_PORT
            seq, ack = c.cseq, c.sseq
        else:
            eth, src, dst, sp, dp = self.ETH_S2C, SERVER_IP, c.ip, SERVER_PORT, c.port
            seq, ack = c.sseq, c.cseq
        n = len(payload) + (1 if flags & 0x03 else 0)  # SYN and FIN take one number
        if c2s:
            c.cseq = (c.cseq + n) & 0xFFFFFFFF
        else:
            c.sseq = (c.sseq + n) & 0xFFFFFFFF
        ip = struct.pack(
            "!BBHHHBBH4s4s", 0x45, 0, 40 + len(payload), self.ip_id, 0x4000, 64, 6, 0, src, dst
        )
        tcp = struct.pack("!HHIIBBHHH", sp, dp, seq, ack, 0x50, flags, 65535, 0, 0)
        frame_len = 54 + len(payload)
        sec, usec = divmod(self.ts_us, 1_000_000)
        self.buf += struct.pack("<IIII", sec, usec, frame_len, frame_len)
        self.buf += eth
        self.buf += ip
        self.buf += tcp
        self.buf += payload
        self.packets += 1
        if len(self.buf) > 1 << 20:
            self.f.write(self.buf)
            self.buf.clear()

    def close(self) -> None:
        self.f.write(self.buf)
        self.buf.clear()


def build_capture(
    adus: int, path: Path, split_anywhere: bool = False, seed: int = 2
) -> dict[str, object]:
    """Write a capture of exactly ``adus`` ADUs (``adus`` even) and return its statistics."""
    rng = random.Random(seed)
    templates = _templates(rng)
    fcs = list(FC_WEIGHTS)
    weights = list(FC_WEIGHTS.values())
    stats: Counter[str] = Counter()
    fc_count: Counter[str] = Counter()
    conns = [
        _Conn(
            bytes((10, 0, 1, i + 2)),
            40000 + i,
            rng.randrange(1 << 32),
            rng.randrange(1 << 32),
            unit=1 + i % 4,
        )
        for i in range(N_CONN)
    ]
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as f:
        w = _Writer(f)
        for c in conns:  # three-way handshakes
            w.seg(c, True, b"", 0x02)
            w.seg(c, False, b"", 0x12)
            w.seg(c, True, b"", 0x10)
        transactions = adus // 2
        done = 0

        def adu_pair(c: _Conn) -> tuple[bytes, bytes]:
            fc = rng.choices(fcs, weights)[0]
            req, resp = templates[fc][rng.randrange(VARIANTS)]
            if rng.random() < P_EXCEPTION:
                resp = encode_exception(fc, rng.randrange(1, 5))
                stats["exceptions"] += 1
            fc_count[f"{fc:02X}"] += 2
            tid = c.tid
            c.tid = (c.tid + 1) & 0xFFFF
            return (
                struct.pack("!HHHB", tid, 0, len(req) + 1, c.unit) + req,
                struct.pack("!HHHB", tid, 0, len(resp) + 1, c.unit) + resp,
            )

        def send(c: _Conn, c2s: bool, data: bytes, split: bool) -> None:
            if split:
                cut = rng.randrange(1 if split_anywhere else 8, len(data))
                w.seg(c, c2s, data[:cut])
                w.seg(c, c2s, data[cut:])
                stats["split ADUs"] += 1
            else:
                w.seg(c, c2s, data)

        while done < transactions:
            c = conns[rng.randrange(N_CONN)]
            if rng.random() < P_PIPELINE and transactions - done >= 2:
                k = min(rng.randrange(2, 5), transactions - done)
                pairs = [adu_pair(c) for _ in range(k)]
                w.seg(c, True, b"".join(p[0] for p in pairs))
                w.seg(c, False, b"".join(p[1] for p in pairs))
                stats["segments with several ADUs"] += 2
                done += k
            else:
                req, resp = adu_pair(c)
                send(c, True, req, rng.random() < P_SPLIT)
                send(c, False, resp, rng.random() < P_SPLIT)
                done += 1
        for c in conns:  # close: FIN both ways, last ACK
            w.seg(c, True, b"", 0x11)
            w.seg(c, False, b"", 0x11)
            w.seg(c, True, b"", 0x10)
        w.close()
    tmp.replace(path)
    return {
        "adus": 2 * transactions,
        "packets": w.packets,
        "connections": N_CONN,
        "bytes": path.stat().st_size,
        **stats,
        "function codes (ADUs)": dict(sorted(fc_count.items())),
    }


def capture(adus: int, split_anywhere: bool = False) -> tuple[Path, dict[str, object]]:
    """The cached capture for ``adus`` ADUs (built when missing) and its statistics."""
    if adus <= 0 or adus % 2:
        raise SystemExit("--adus must be a positive even number (request + response pairs)")
    OUT.mkdir(parents=True, exist_ok=True)
    tag = "_anysplit" if split_anywhere else ""
    path = OUT / f"modbus_tcp_{adus}{tag}_v{GEN_VERSION}.pcap"
    meta = path.with_suffix(".json")
    if path.exists() and meta.exists():
        return path, json.loads(meta.read_text())
    t0 = time.perf_counter()
    stats = build_capture(adus, path, split_anywhere)
    stats["build seconds"] = round(time.perf_counter() - t0, 1)
    meta.write_text(json.dumps(stats, indent=1))
    return path, stats


# --------------------------------------------------------------------------- measuring


@dataclass
class Run:
    name: str
    cmd: list[str]
    wall: float
    rss_mb: float
    user: float
    sys: float
    lines: int
    adus: int  # ADUs the tool reported
    rc: int


def tshark_cmd(path: Path) -> list[str]:
    """The anchor's command: tshark dissecting every Modbus/TCP ADU of ``path`` and
    printing three fields of each (its cheapest complete pass over the file)."""
    fields = ("mbtcp.trans_id", "modbus.func_code", "modbus.reference_num")
    return ["tshark", "-r", str(path), "-Y", "modbus", "-T", "fields"] + [
        arg for field in fields for arg in ("-e", field)
    ]


def measure(name: str, cmd: list[str], count: str | None) -> Run:
    """Run ``cmd`` as one child, stdout to /dev/null (``count=None``) or counted through a pipe.

    ``count`` = "mbmon": count JSON records whose kind is request, response or
    exception; "tshark": count function-code values (one per ADU, comma-joined
    when one frame carries several). Counting happens in this process while the
    child runs and only costs the child the pipe writes.
    """
    t0 = time.perf_counter()
    stdout = subprocess.DEVNULL if count is None else subprocess.PIPE
    p = subprocess.Popen(cmd, stdout=stdout, stderr=subprocess.PIPE)
    lines = adus = 0
    tail = b""
    if p.stdout is not None:
        while block := p.stdout.read(1 << 20):
            lines += block.count(b"\n")
            data = tail + block  # count complete lines only: a block can end mid-record
            cut = data.rfind(b"\n") + 1
            done, tail = data[:cut], data[cut:]
            if count == "mbmon":
                for k in (b'"request"', b'"response"', b'"exception"'):
                    adus += done.count(b'"kind": ' + k) + done.count(b'"kind":' + k)
            else:
                for line in done.splitlines():
                    if line:
                        adus += line.split(b"\t")[1].count(b",") + 1
    assert p.stderr is not None
    err = p.stderr.read()
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        sys.stderr.write(err.decode(errors="replace")[-2000:])
    return Run(
        name, cmd, wall, ru.ru_maxrss / 1024, ru.ru_utime, ru.ru_stime, lines, adus, p.returncode
    )


def mbmon_cmd() -> list[str]:
    """``python -m mbmon`` of this tree (never an ``mbmon`` script installed from another)."""
    repo = str(Path(__file__).resolve().parents[1])
    path = os.environ.get("PYTHONPATH", "")
    if path.split(os.pathsep)[0] != repo:
        os.environ["PYTHONPATH"] = repo + (os.pathsep + path if path else "")
    return [sys.executable, "-m", "mbmon"]


def show(run: Run, n: int) -> None:
    rate = n / run.wall
    seen = f", {run.adus:,} ADUs in output" if run.adus else ""
    print(
        f"  {run.name:<26} {run.wall:8.2f} s  {rate:>12,.0f} ADUs/s"
        f"  peak RSS {run.rss_mb:7.1f} MB"
        f"  (user {run.user:.1f} s, sys {run.sys:.1f} s, exit {run.rc}{seen})"
    )


def profile(adus: int, top: int = 25) -> None:
    """cProfile ``mbmon read --json`` in this process, output discarded; print the hot spots."""
    path, _ = capture(adus)
    from mbmon.cli import main

    prof = cProfile.Profile()
    real = sys.stdout
    with open(os.devnull, "w") as null:
        sys.stdout = null
        try:
            prof.enable()
            main(["read", str(path), "--json"])
            prof.disable()
        finally:
            sys.stdout = real
    out = OUT / f"profile_{adus}.prof"
    prof.dump_stats(out)
    st = pstats.Stats(prof)
    total = st.total_tt  # type: ignore[attr-defined]
    rows = []
    for (file, line, func), (_cc, nc, tt, ct, _callers) in st.stats.items():  # type: ignore[attr-defined]
        rows.append((tt, ct, nc, f"{Path(file).name}:{line}:{func}"))
    print(f"cProfile of mbmon read --json on {adus:,} ADUs: {total:.1f} s total (saved to {out})")
    print(f"  {'own %':>6} {'own s':>7} {'cum %':>6} {'calls':>10}  function")
    for tt, ct, nc, name in sorted(rows, reverse=True)[:top]:
        print(f"  {100 * tt / total:6.1f} {tt:7.2f} {100 * ct / total:6.1f} {nc:10,}  {name}")
    per_file: Counter[str] = Counter()
    for (file, _line, _func), (_cc, _nc, tt, _ct, _callers) in st.stats.items():  # type: ignore[attr-defined]
        per_file[file if "mbmon" in file else Path(file).name] += tt
    print("  own time per file:")
    for file, tt in per_file.most_common(12):
        shown = file.split("/mbmon/", 1)[-1] if "/mbmon/" in file else file
        print(f"  {100 * tt / total:6.1f} {tt:7.2f}  {shown}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--adus", type=int, default=1_000_000, help="ADUs in the capture (even)")
    ap.add_argument("--skip-tshark", action="store_true", help="time mbmon only")
    ap.add_argument(
        "--flat",
        action="store_true",
        help="also run mbmon on a capture of N/4 ADUs and compare peak RSS",
    )
    ap.add_argument(
        "--mcap", action="store_true", help="also time mbmon read -q -w x.mcap and -w x.jsonl"
    )
    ap.add_argument(
        "--split-anywhere",
        action="store_true",
        help="cut split ADUs anywhere, also inside the MBAP header (tshark loses sync)",
    )
    ap.add_argument(
        "--devnull",
        action="store_true",
        help="send stdout to /dev/null instead of counting it through a pipe",
    )
    ap.add_argument(
        "--profile",
        type=int,
        metavar="N",
        help="only profile mbmon read --json on a capture of N ADUs",
    )
    args = ap.parse_args(argv)
    if args.profile:
        profile(args.profile)
        return 0

    n = args.adus
    path, stats = capture(n, args.split_anywhere)
    print(
        f"capture: {path.relative_to(REPO)}"
        f"  ({stats['bytes']:,} bytes, {stats['packets']:,} packets)"
    )
    print("  " + json.dumps({k: v for k, v in stats.items() if k not in ("bytes", "packets")}))
    load = os.getloadavg()
    print(
        f"machine: {os.cpu_count()} CPUs,"
        f" load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f};"
        f" python {sys.version.split()[0]}"
    )
    mode = None if args.devnull else "mbmon"
    runs: list[tuple[Run, int]] = []
    mb = measure("mbmon read --json", [*mbmon_cmd(), "read", str(path), "--json"], mode)
    runs.append((mb, n))
    ts = None
    if not args.skip_tshark:
        if shutil.which("tshark") is None:
            print("tshark not installed: skipped")
        else:
            ts = measure("tshark -T fields", tshark_cmd(path), None if args.devnull else "tshark")
            runs.append((ts, n))
    small = None
    if args.flat:
        m = n // 4 - (n // 4) % 2
        spath, _ = capture(m, args.split_anywhere)
        small = measure(
            f"mbmon read --json ({m:,})", [*mbmon_cmd(), "read", str(spath), "--json"], mode
        )
        runs.append((small, m))
    if args.mcap:
        for suffix in ("jsonl", "mcap"):
            target = OUT / f"bench.{suffix}"
            target.unlink(missing_ok=True)
            r = measure(
                f"mbmon read -q -w x.{suffix}",
                [*mbmon_cmd(), "read", str(path), "-q", "-w", str(target)],
                None,
            )
            runs.append((r, n))
            if target.exists():
                print(f"  (x.{suffix}: {target.stat().st_size:,} bytes)")
                target.unlink()  # a 1M-ADU .jsonl is about 1 GB

    how = "stdout to /dev/null" if args.devnull else "stdout counted through a pipe"
    print(f"results ({how}):")
    for run, k in runs:
        show(run, k)
    failed = [run.name for run, _ in runs if run.rc != 0]
    if failed:
        print(f"  !! failed (see the error above): {', '.join(failed)}; no verdict")
        return 1
    ok = True
    if mode and mb.adus != n:
        print(f"  !! mbmon reported {mb.adus:,} ADUs, the capture holds {n:,}")
        ok = False
    if ts and not args.devnull and ts.adus != n:
        print(f"  !! tshark reported {ts.adus:,} ADUs, the capture holds {n:,}")
    if ts is not None:
        ratio = ts.wall / mb.wall
        print(
            f"  mbmon / tshark ADUs/s: {ratio:.2f}x (target >= {TARGET_RATIO:.0f}x)"
            f" -> {'met' if ratio >= TARGET_RATIO else 'NOT met'}"
        )
        cpu = (ts.user + ts.sys) / (mb.user + mb.sys)
        print(f"  same by CPU time (user+sys), less sensitive to other load: {cpu:.2f}x")
        ok &= ratio >= TARGET_RATIO
    print(
        f"  mbmon peak RSS {mb.rss_mb:.1f} MB (target < {TARGET_RSS_MB:.0f} MB)"
        f" -> {'met' if mb.rss_mb < TARGET_RSS_MB else 'NOT met'}"
    )
    ok &= mb.rss_mb < TARGET_RSS_MB
    if small is not None:
        growth = mb.rss_mb - small.rss_mb
        print(
            f"  RSS {small.rss_mb:.1f} MB at {n // 4:,} ADUs vs {mb.rss_mb:.1f} MB at {n:,}:"
            f" {growth:+.1f} MB for 4x the ADUs"
        )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
