"""The pure-Python fallback (``MBMON_NO_EXTENSIONS=1``) next to the pipeline as it was
before the compiled core existed, in the same run: did the split cost the fallback?

    python bench/pure_fallback.py                      # 1,000,000 ADUs, 3 rounds
    python bench/pure_fallback.py --adus 200000 --rounds 5
    python bench/pure_fallback.py --baseline 12ba4c0   # another tree to compare with

What this script owns: the baseline tree (a ``git worktree`` of ``--baseline`` in
bench/out/, made once and reused) and the alternating runs. Each round runs
``read F`` (text) and ``read F --json`` of the baseline and of this tree forced
pure, one after the other, each as its own child with stdout to /dev/null; the
figure is the best CPU time (user + sys of the child) over the rounds, so a busy
moment on the shared machine costs neither side. The file is bench/realistic.py's
aligned capture (cached in bench/out/).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO))
from read_throughput import measure  # noqa: E402
from realistic import OUT, capture  # noqa: E402

# The last commit before the compiled core: its pipeline is the one the fallback
# must not be slower than.
BEFORE_CORE = "12ba4c03834d92ab154cbb8d4854ad01a05df99d"


def baseline_tree(rev: str) -> Path:
    """A worktree of ``rev`` under bench/out/ (made once; reused while it is that rev)."""
    tree = OUT / f"baseline-{rev[:10]}"
    if not (tree / "mbmon").is_dir():
        subprocess.run(
            ["git", "-C", str(REPO), "worktree", "add", "--detach", str(tree), rev], check=True
        )
    return tree


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--adus", type=int, default=1_000_000, help="ADUs in the capture (even)")
    ap.add_argument("--rounds", type=int, default=3, help="alternating rounds (best CPU counts)")
    ap.add_argument("--baseline", default=BEFORE_CORE, help="the tree to compare with (a commit)")
    args = ap.parse_args()
    path = capture("polling", args.adus, 8, 2, "aligned")
    tree = baseline_tree(args.baseline)
    env_pure = ["env", "MBMON_NO_EXTENSIONS=1", f"PYTHONPATH={REPO}"]
    env_base = ["env", "MBMON_NO_EXTENSIONS=1", f"PYTHONPATH={tree}"]
    py = sys.executable
    rows = {
        "baseline: read (text)": [*env_base, py, "-m", "mbmon", "read", str(path)],
        "pure now: read (text)": [*env_pure, py, "-m", "mbmon", "read", str(path)],
        "baseline: read --json": [*env_base, py, "-m", "mbmon", "read", str(path), "--json"],
        "pure now: read --json": [*env_pure, py, "-m", "mbmon", "read", str(path), "--json"],
    }
    best: dict[str, float] = {}
    print(f"file: {path} ({args.adus:,} ADUs); baseline {args.baseline[:10]} at {tree}")
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    for r in range(args.rounds):
        for name, cmd in rows.items():
            run = measure(name, cmd, None)
            cpu = run.user + run.sys
            if run.rc != 0:
                print(f"  {name}: exit {run.rc}")
                return 1
            best[name] = min(best.get(name, cpu), cpu)
            print(f"  round {r + 1} {name:24} CPU {cpu:7.2f} s  peak RSS {run.rss_mb:6.1f} MB")
    print(f"load average at end: {os.getloadavg()[0]:.2f}")
    print("best CPU per row, and now / baseline:")
    for mode in ("text", "--json"):
        b = next(v for k, v in best.items() if k.startswith("baseline") and mode in k)
        n = next(v for k, v in best.items() if k.startswith("pure now") and mode in k)
        print(f"  {mode:7} baseline {b:7.2f} s  pure now {n:7.2f} s  ratio {n / b:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
