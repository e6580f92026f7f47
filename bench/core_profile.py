"""``mbmon read --profile hrss`` by the compiled core, next to tshark's best case, the
core without a profile and the pure-Python pipeline with it, in the same run (CPU
time, wall time, peak RSS; callgrind instructions).

    python bench/core_profile.py                     # the 200,000-ADU HRSS file
    python bench/core_profile.py --adus 1000000
    python bench/core_profile.py --callgrind 100000  # + instructions per ADU (marginal)

What this script owns: the runs and the figures for profiles on the core
(docs/performance.md records them). The capture is bench/realistic.py's HRSS cell
(cached in bench/out/: a PLC polling IR500..IR523, IR524 and IR200 every cycle,
joints moving on every poll, a command written and executed every 25 cycles), one
ADU per TCP segment. The anchor is tshark's best case, ``tshark -r F -Y mbtcp >
/dev/null``; every mbmon run writes to /dev/null too. Ratios are by CPU time (user +
sys of the one child: the machine is shared). Callgrind figures are marginal:
(I(N) - I(N/5)) / (4N/5), so start-up and imports cancel out.
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
import subprocess  # noqa: E402

from core_read import _instructions, _pure, cpu  # noqa: E402
from read_throughput import Run, mbmon_cmd, measure  # noqa: E402
from realistic import capture  # noqa: E402

TARGET = 2.0  # --profile hrss, x tshark's best case, by CPU


def _which_path(mb: list[str], path: Path) -> str:
    """What ``--debug-core`` says for ``read --profile hrss`` (the core must have run)."""
    done = subprocess.run(
        [*mb, "read", str(path), "--profile", "hrss", "-q", "--debug-core"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    return next((ln for ln in done.stderr.splitlines() if "core:" in ln), "?").strip()


def callgrind_figures(n: int) -> None:
    """Marginal instructions per ADU on the HRSS cell, with and without the profile."""
    if not shutil.which("valgrind"):
        print("  (valgrind is missing: no instruction counts)")
        return
    k = n - n % 10
    small = capture("hrss", k // 5, 1, 0, "aligned")
    big = capture("hrss", k, 1, 0, "aligned")
    py = [sys.executable, "-m", "mbmon", "read"]
    for label, extra, pure in (
        ("core: read (text)", [], False),
        ("core: read --profile hrss", ["--profile", "hrss"], False),
        ("core: read --profile hrss --json", ["--profile", "hrss", "--json"], False),
        ("pure: read --profile hrss", ["--profile", "hrss"], True),
    ):
        lo = _instructions([*py, str(small), *extra], pure=pure)
        hi = _instructions([*py, str(big), *extra], pure=pure)
        print(f"  callgrind instructions per ADU, {label}: {(hi - lo) / (k - k // 5):,.0f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--adus", type=int, default=200_000, help="ADUs in the capture (even)")
    ap.add_argument("--callgrind", type=int, metavar="N", help="instructions per ADU at N ADUs")
    ap.add_argument("--skip-pure", action="store_true", help="no pure-Python run")
    args = ap.parse_args(argv)
    load = os.getloadavg()
    print(f"machine: {os.cpu_count()} CPUs, load average {load[0]:.2f} {load[1]:.2f}"
          f" {load[2]:.2f}; python {sys.version.split()[0]}")  # fmt: skip
    hrss = capture("hrss", args.adus, 1, 0, "aligned")
    mb = mbmon_cmd()
    print(f"  {hrss.name} --profile hrss: {_which_path(mb, hrss)}")
    runs: dict[str, Run] = {}
    if shutil.which("tshark"):
        runs["tshark"] = measure("tshark -Y mbtcp (best case)", ["tshark", "-r", str(hrss),
                                 "-Y", "mbtcp"], None)  # fmt: skip
    profile = [*mb, "read", str(hrss), "--profile", "hrss"]
    runs["plain"] = measure("core: read (no profile)", [*mb, "read", str(hrss)], None)
    runs["profile"] = measure("core: read --profile hrss", profile, None)
    runs["json"] = measure("core: --profile hrss --json", [*profile, "--json"], None)
    if not args.skip_pure:
        runs["pure"] = measure("pure: read --profile hrss", _pure(profile), None)
    print("results (CPU = user + sys of the child):")
    for run in runs.values():
        print(f"  {run.name:<30} CPU {cpu(run):7.2f} s  wall {run.wall:7.2f} s"
              f"  peak RSS {run.rss_mb:7.1f} MB  exit {run.rc}")  # fmt: skip
    print("verdicts:")
    ts = runs.get("tshark")
    if ts is not None:
        for key in ("profile", "json"):
            ratio = cpu(ts) / cpu(runs[key])
            verdict = "met" if ratio >= TARGET else "NOT met"
            target = f" (target >= {TARGET}x) -> {verdict}" if key == "profile" else ""
            print(f"  {runs[key].name} vs tshark's best case, CPU: {ratio:.2f}x{target}")
    print(f"  --profile hrss / no profile (core), CPU: "
          f"{cpu(runs['profile']) / cpu(runs['plain']):.2f}x")  # fmt: skip
    if "pure" in runs:
        print(f"  core vs pure Python (--profile hrss), CPU: "
              f"{cpu(runs['pure']) / cpu(runs['profile']):.1f}x")  # fmt: skip
    if args.callgrind:
        callgrind_figures(args.callgrind)
    return 0


if __name__ == "__main__":
    sys.exit(main())
