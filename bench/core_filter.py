"""``mbmon read`` with filters and ``-c`` by the compiled core, next to tshark's best
case, the unfiltered core read and the pure-Python pipeline, in the same run (CPU
time of the child, peak RSS).

    python bench/core_filter.py                 # 1,000,000 ADUs (realistic.py's files)
    python bench/core_filter.py --adus 200000
    python bench/core_filter.py --skip-pure

What this script owns: the figures of the core's filtered reads (docs/performance.md,
"Filters and -c on the core"). The capture is bench/realistic.py's ``aligned`` file
(one ADU per TCP segment: tshark's best case, the anchor ``tshark -r F -Y mbtcp >
/dev/null``); every run writes to /dev/null. Ratios are by CPU time (user + sys of
the one child: the machine is shared).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO))
from core_read import _pure, _which_path, cpu  # noqa: E402
from read_throughput import Run, mbmon_cmd, measure  # noqa: E402
from realistic import capture  # noqa: E402

#: the filtered reads measured: name -> read's options
READS = {
    "text": [],
    "--fc 3": ["--fc", "3"],
    "--fc 3 --json": ["--fc", "3", "--json"],
    "--unit 1 --address 0-10": ["--unit", "1", "--address", "0-10"],
    "--grep Holding": ["--grep", "Holding"],
    "-c 500000 --fc 3": ["-c", "500000", "--fc", "3"],
    "--where 'fc 3'": ["--where", "fc 3"],
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--adus", type=int, default=1_000_000, help="ADUs in the capture (even)")
    ap.add_argument("--skip-pure", action="store_true", help="no pure-Python run")
    args = ap.parse_args(argv)
    load = os.getloadavg()
    print(f"machine: {os.cpu_count()} CPUs, load average {load[0]:.2f} {load[1]:.2f}"
          f" {load[2]:.2f}; python {sys.version.split()[0]}")  # fmt: skip
    aligned = capture("polling", args.adus, 8, 2, "aligned")
    mb = mbmon_cmd()
    print(f"  {aligned.name}: {_which_path(mb, aligned)}")
    runs: dict[str, Run] = {}
    if shutil.which("tshark"):
        runs["tshark"] = measure("tshark -Y mbtcp (aligned)", ["tshark", "-r", str(aligned),
                                 "-Y", "mbtcp"], None)  # fmt: skip
    for name, opts in READS.items():
        runs[name] = measure(f"core: read {name}", [*mb, "read", str(aligned), *opts], None)
    if not args.skip_pure:
        runs["pure --fc 3"] = measure(
            "pure: read --fc 3", _pure([*mb, "read", str(aligned), "--fc", "3"]), None
        )
    print("results (CPU = user + sys of the child):")
    for run in runs.values():
        print(f"  {run.name:<34} CPU {cpu(run):7.2f} s  wall {run.wall:7.2f} s"
              f"  peak RSS {run.rss_mb:7.1f} MB  exit {run.rc}")  # fmt: skip
    print("ratios:")
    ts = runs.get("tshark")
    for name in READS:
        if ts is not None:
            print(f"  read {name} vs tshark's best case, CPU: {cpu(ts) / cpu(runs[name]):.2f}x")
        if name != "text":
            print(f"  read {name} / unfiltered read, CPU: "
                  f"{cpu(runs[name]) / cpu(runs['text']):.2f}")  # fmt: skip
    if "pure --fc 3" in runs:
        print(f"  core vs pure Python (--fc 3), CPU: "
              f"{cpu(runs['pure --fc 3']) / cpu(runs['--fc 3']):.1f}x")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
