"""``mbmon read`` by the compiled core, next to tshark's best case and the pure-Python
pipeline, in the same run (CPU time, wall time, peak RSS; callgrind instructions).

    python bench/core_read.py                      # 1,000,000 ADUs (realistic.py's files)
    python bench/core_read.py --adus 200000
    python bench/core_read.py --callgrind 100000   # + instructions per ADU (marginal)
    python bench/core_read.py --flat               # + 5x the ADUs: is peak RSS flat?
    python bench/core_read.py --against /tmp/old   # + this tree's core against another's

With a log (``-w x.mcap``, written to bench/out/ and removed): ``read -q -w x.mcap``
and ``read -w x.mcap`` (console text and the log at once), core and pure, and the
cost of the log's chunk compression on the same bytes (its uncompressed chunks
compressed again in this process with the writer's zstd level, and with level 1;
the CRC-32 of them), measured in the same run.

What this script owns: the runs and the figures for the core (docs/performance.md
records them). The captures are bench/realistic.py's (cached in bench/out/): the
``aligned`` file (one ADU per TCP segment: tshark's best case, the anchor) and the
``mixed`` one (8 % multi-ADU segments, 2 % split ADUs). The anchor is
``tshark -r F -Y mbtcp > /dev/null``; every mbmon run writes to /dev/null too.
Ratios are by CPU time (user + sys of the one child: the machine is shared).
Callgrind figures are marginal: (I(N) - I(N/5)) / (4N/5), so start-up and imports
cancel out.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO))
from read_throughput import Run, mbmon_cmd, measure  # noqa: E402
from realistic import OUT, capture  # noqa: E402

TARGETS = {"text": 10.0, "json": 8.0, "mcap-q": 5.0}  # x tshark's best case, by CPU
MIXED = 1.25  # mixed / aligned, at most
MAX_RSS_MB = 100.0


def _pure(cmd: list[str]) -> list[str]:
    return ["env", "MBMON_NO_EXTENSIONS=1", *cmd]


def _which_path(mb: list[str], path: Path) -> str:
    """What ``--debug-core`` says for this file (the core must really have run)."""
    done = subprocess.run(
        [*mb, "read", str(path), "-q", "--debug-core"], capture_output=True, text=True, check=False
    )
    return next((ln for ln in done.stderr.splitlines() if "core:" in ln), "?").strip()


def _instructions(cmd: list[str], *, pure: bool = False) -> int:
    out = OUT / "core-callgrind.out"
    env = dict(os.environ, MBMON_NO_EXTENSIONS="1") if pure else None
    subprocess.run(
        ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", *cmd],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO, check=False, env=env,
    )  # fmt: skip
    text = out.read_text(errors="replace")
    out.unlink()
    return int(next(ln for ln in text.splitlines() if ln.startswith("summary:")).split()[1])


def cpu(run: Run) -> float:
    return run.user + run.sys


def compression_cost(log: Path) -> dict[str, float]:
    """CPU seconds this process spends compressing (zstd at the writer's level, and at
    level 1) and checksumming the uncompressed chunks of ``log``, their size, the bytes
    of each topic's message records, and the zstd cost of the same chunks without the
    /modbus/monitor messages (what storing the monitor line would cost)."""
    import struct
    import time
    import zlib

    import zstandard
    from mcap.reader import make_reader
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    from mbmon.io.mcap.writer import ZSTD_LEVEL

    with open(log, "rb") as f:
        summary = make_reader(f).get_summary()
        topic_of = {cid: ch.topic for cid, ch in summary.channels.items()} if summary else {}
    out: dict[str, float] = {"bytes": 0.0}
    monitor = next((c for c, t in topic_of.items() if t == "/modbus/monitor"), -1)
    level = zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress
    fns = (
        (f"zstd {ZSTD_LEVEL}", level, False),
        *((("zstd 3", zstandard.ZstdCompressor(level=3).compress, False),) * (ZSTD_LEVEL != 3)),
        ("zstd 1", zstandard.ZstdCompressor(level=1).compress, False),
        ("crc32", zlib.crc32, False),
        (f"zstd {ZSTD_LEVEL} without /modbus/monitor", level, True),
    )
    with open(log, "rb") as f:  # one chunk at a time: this process stays small
        for record in StreamReader(f, skip_magic=False, emit_chunks=True).records:
            if not isinstance(record, Chunk):
                continue
            chunk = zstandard.ZstdDecompressor().decompress(
                record.data, max_output_size=record.uncompressed_size)  # fmt: skip
            out["bytes"] += len(chunk)
            p, keep = 0, []
            while p < len(chunk):  # message records: opcode, length, channel, ... (MESSAGE_HEAD)
                length, channel = struct.unpack_from("<QH", chunk, p + 1)
                end = p + 9 + length
                key = "topic " + topic_of.get(channel, str(channel))
                out[key] = out.get(key, 0.0) + (end - p)
                if channel != monitor:
                    keep.append(chunk[p:end])
                p = end
            without = b"".join(keep)
            for label, fn, lighter in fns:
                t0 = time.process_time()
                fn(without if lighter else chunk)
                out[label] = out.get(label, 0.0) + time.process_time() - t0
    return out


def against(other: Path, aligned: Path, rounds: int) -> None:
    """This tree's core against another tree's (a copy with its core built: the tree
    before a change), ``rounds`` alternated rounds of text, ``--json``, ``-q -w`` and
    ``-w`` on the aligned file: best and median CPU of each, and this tree's best over
    the other's (the machine's load moves both alike)."""
    import statistics

    log = OUT / "core-against.mcap"
    modes = {"text": [], "--json": ["--json"], "-q -w": ["-q", "-w", str(log)],
             "-w": ["-w", str(log)]}  # fmt: skip
    trees = {"this": REPO, "other": other.resolve()}
    cpus: dict[tuple[str, str], list[float]] = {(t, m): [] for t in trees for m in modes}
    for r in range(rounds):
        for mode, extra in modes.items():
            order = list(trees.items()) if r % 2 == 0 else list(trees.items())[::-1]
            for tree, root in order:
                # the tree's own mbmon first on the path: its directory and PYTHONPATH
                cmd = ["env", "-C", str(root), f"PYTHONPATH={root}", sys.executable, "-m",
                       "mbmon", "read", str(aligned), *extra]  # fmt: skip
                cpus[(tree, mode)].append(cpu(measure(f"{tree}: {mode}", cmd, None)))
    log.unlink(missing_ok=True)
    print(f"this tree against {other} ({rounds} alternated rounds, CPU of the child):")
    for mode in modes:
        a, b = cpus[("this", mode)], cpus[("other", mode)]
        print(f"  read {mode:<7} this: best {min(a):.3f} s, median {statistics.median(a):.3f}"
              f"  other: best {min(b):.3f} s, median {statistics.median(b):.3f}"
              f"  -> {min(a) / min(b):.3f}x")  # fmt: skip


def callgrind_figures(n: int) -> None:
    """Marginal instructions per ADU: (I(n) - I(n/5)) / (4n/5), core and pure."""
    if not shutil.which("valgrind"):
        print("  (valgrind is missing: no instruction counts)")
        return
    k = n - n % 10
    small = capture("polling", k // 5, 8, 2, "aligned")
    big = capture("polling", k, 8, 2, "aligned")
    py = [sys.executable, "-m", "mbmon", "read"]
    log = str(OUT / "core-callgrind.mcap")
    for label, extra, pure in (
        ("core: read (text)", [], False),
        ("core: read --json", ["--json"], False),
        ("core: read -q -w x.mcap", ["-q", "-w", log], False),
        ("pure: read (text)", [], True),
        ("pure: read --json", ["--json"], True),
        ("pure: read -q -w x.mcap", ["-q", "-w", log], True),
    ):
        lo = _instructions([*py, str(small), *extra], pure=pure)
        hi = _instructions([*py, str(big), *extra], pure=pure)
        print(f"  callgrind instructions per ADU, {label}: {(hi - lo) / (k - k // 5):,.0f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--adus", type=int, default=1_000_000, help="ADUs per capture (even)")
    ap.add_argument("--callgrind", type=int, metavar="N", help="instructions per ADU at N ADUs")
    ap.add_argument("--flat", action="store_true", help="also 5x the ADUs: peak RSS flat?")
    ap.add_argument("--skip-pure", action="store_true", help="no pure-Python runs")
    ap.add_argument("--callgrind-only", action="store_true", help="only the callgrind figures")
    ap.add_argument(
        "--against",
        type=Path,
        metavar="DIR",
        help="also this tree's core against DIR's (another tree, its core built)",
    )
    ap.add_argument("--rounds", type=int, default=3, help="alternated rounds for --against")
    args = ap.parse_args(argv)
    load = os.getloadavg()
    print(f"machine: {os.cpu_count()} CPUs, load average {load[0]:.2f} {load[1]:.2f}"
          f" {load[2]:.2f}; python {sys.version.split()[0]}")  # fmt: skip
    if args.callgrind_only:
        callgrind_figures(args.callgrind or 100_000)
        return 0
    n = args.adus
    aligned = capture("polling", n, 8, 2, "aligned")
    mixed = capture("polling", n, 8, 2, "mixed")
    mb = mbmon_cmd()
    for path in (aligned, mixed):
        print(f"  {path.name}: {_which_path(mb, path)}")
    runs: dict[str, Run] = {}
    if shutil.which("tshark"):
        runs["tshark"] = measure("tshark -Y mbtcp (aligned)", ["tshark", "-r", str(aligned),
                                 "-Y", "mbtcp"], None)  # fmt: skip
    runs["text"] = measure("core: read (text)", [*mb, "read", str(aligned)], None)
    runs["json"] = measure("core: read --json", [*mb, "read", str(aligned), "--json"], None)
    runs["mixed"] = measure("core: read (text, mixed)", [*mb, "read", str(mixed)], None)
    log = OUT / "core-read.mcap"
    logged = [*mb, "read", str(aligned), "-w", str(log)]
    runs["mcap-q"] = measure("core: read -q -w x.mcap", [*logged, "-q"], None)
    runs["mcap"] = measure("core: read -w x.mcap", logged, None)
    if not args.skip_pure:
        runs["pure-text"] = measure("pure: read (text)", _pure([*mb, "read", str(aligned)]), None)
        runs["pure-json"] = measure(
            "pure: read --json", _pure([*mb, "read", str(aligned), "--json"]), None
        )
        runs["pure-mcap-q"] = measure("pure: read -q -w x.mcap", _pure([*logged, "-q"]), None)
        runs["pure-mcap"] = measure("pure: read -w x.mcap", _pure(logged), None)
    if args.flat:
        big = capture("polling", 5 * n, 8, 2, "aligned")
        print(f"  {big.name}: {_which_path(mb, big)}")
        runs["flat"] = measure(f"core: read --json ({5 * n:,})", [*mb, "read", str(big),
                               "--json"], None)  # fmt: skip
    # after every run: the children are forked from this process, whose pages count in
    # their peak RSS until they exec
    cost = compression_cost(log)
    log.unlink(missing_ok=True)
    print("results (CPU = user + sys of the child):")
    for run in runs.values():
        print(f"  {run.name:<28} CPU {cpu(run):7.2f} s  wall {run.wall:7.2f} s"
              f"  peak RSS {run.rss_mb:7.1f} MB  exit {run.rc}")  # fmt: skip
    print("verdicts:")
    ts = runs.get("tshark")
    for key in ("text", "json", "mcap-q"):
        if ts is not None:
            ratio = cpu(ts) / cpu(runs[key])
            ok = "met" if ratio >= TARGETS[key] else "NOT met"
            print(f"  {key} vs tshark's best case, CPU: {ratio:.2f}x (target >= "
                  f"{TARGETS[key]}x) -> {ok}")  # fmt: skip
    ratio = cpu(runs["mixed"]) / cpu(runs["text"])
    print(f"  mixed / aligned CPU: {ratio:.2f} (target <= {MIXED}) -> "
          f"{'met' if ratio <= MIXED else 'NOT met'}")  # fmt: skip
    if ts is not None:
        print(f"  read -w x.mcap (console and log) vs tshark's best case, CPU: "
              f"{cpu(ts) / cpu(runs['mcap']):.2f}x")  # fmt: skip
    mb_log = cost["bytes"] / 1e6
    print(f"  the log's chunks: {mb_log:,.0f} MB uncompressed, {cost['bytes'] / n:,.0f} bytes"
          " per ADU: " + ", ".join(f"{k[6:]} {v / n:,.0f}" for k, v in cost.items()
                                   if k.startswith("topic ")))  # fmt: skip
    for k, v in cost.items():
        if k != "bytes" and not k.startswith("topic "):
            print(f"    {k}: {v:.2f} s CPU in this process ({v / cpu(runs['mcap-q']):.0%} of"
                  " the core's -q -w run)")  # fmt: skip
    if "pure-text" in runs:
        for key in ("text", "json", "mcap-q", "mcap"):
            print(f"  core vs pure Python ({key}), CPU: "
                  f"{cpu(runs['pure-' + key]) / cpu(runs[key]):.1f}x")  # fmt: skip
    peak = max(run.rss_mb for key, run in runs.items() if key != "tshark")
    print(f"  peak RSS of mbmon runs: {peak:.1f} MB (target < {MAX_RSS_MB:.0f} MB)")
    if "flat" in runs:
        print(f"  RSS at 5x / 1x: {runs['flat'].rss_mb / runs['json'].rss_mb:.2f}")
    if args.against is not None:
        against(args.against, aligned, args.rounds)
    if args.callgrind:
        callgrind_figures(args.callgrind)
    return 0


if __name__ == "__main__":
    sys.exit(main())
