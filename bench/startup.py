"""The fixed cost of an ``mbmon`` run (interpreter start-up, imports, the parser,
module set-up): CPU of whole processes, this tree next to another one in the same run.

    python bench/startup.py                          # this tree alone
    python bench/startup.py --against /tmp/old-tree  # and a checkout of another commit
    python bench/startup.py --rounds 15 --big        # + read -q -w x.mcap on the 1M file

Every command runs ``--rounds`` times, the trees alternating within each round (so
the load moves both alike); the figure is the median CPU (user + sys of the one
child, from ``os.wait4``) and, for reference, the median wall time. ``python3 -c
pass`` is the interpreter's own floor (site and the editable install's finder: not
mbmon's). Each tree runs as ``python -m mbmon`` from its own root, so its own
``mbmon`` package is the one imported (the compiled core too, when the tree has it
built in place).

What this script owns: the start-up figures in docs/performance.md ("The fixed
cost of a run").
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEMO = "captures/demo.pcap"
BIG = REPO / "bench" / "out" / "real_polling_1000000_8c2h_aligned_v1.pcap"
#: the children write and use their bytecode (as an installed package has it): without
#: it every run would compile every module it imports, which is not a run's fixed cost
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def commands(log: str, big: bool) -> dict[str, list[str]]:
    """The runs measured, by name (arguments after ``python``)."""
    mb = ["-m", "mbmon"]
    runs = {
        "python -c pass": ["-c", "pass"],
        "--version": [*mb, "--version"],
        "--help": [*mb, "--help"],
        "read --help": [*mb, "read", "--help"],
        "read demo -q": [*mb, "read", DEMO, "-q"],
        "read demo (text)": [*mb, "read", DEMO],
        "read demo --json": [*mb, "read", DEMO, "--json"],
        "read demo -q -w x.mcap": [*mb, "read", DEMO, "-q", "-w", log],
        "read demo --profile hrss -q": [*mb, "read", DEMO, "-q", "--profile", "hrss"],
        "info x.mcap": [*mb, "info", log],
        "decode 03 00 00 00 02": [*mb, "decode", "03 00 00 00 02"],
    }
    if big:
        runs["read 1M -q -w x.mcap"] = [*mb, "read", str(BIG), "-q", "-w", log]
    return runs


def cpu_of(argv: list[str], cwd: Path) -> tuple[float, float, int]:
    """CPU seconds (user + sys), wall seconds and exit status of one child."""
    start = time.perf_counter()
    with open(os.devnull, "wb") as null:
        p = subprocess.Popen([sys.executable, *argv], cwd=cwd, stdout=null, stderr=null, env=ENV)
    _, status, ru = os.wait4(p.pid, 0)
    return ru.ru_utime + ru.ru_stime, time.perf_counter() - start, os.waitstatus_to_exitcode(status)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--against", type=Path, help="another tree (a checkout) to run alongside")
    ap.add_argument("--rounds", type=int, default=11)
    ap.add_argument("--big", action="store_true", help=f"also read -q -w x.mcap on {BIG.name}")
    ap.add_argument("--only", action="append", default=[], help="only runs whose name has this")
    args = ap.parse_args(argv)
    if args.big and not BIG.exists():
        print(f"{BIG} is missing: python bench/realistic.py makes it", file=sys.stderr)
        return 1
    trees = {"this": REPO}
    if args.against is not None:
        trees["against"] = args.against.resolve()
    with tempfile.TemporaryDirectory() as tmp:
        log = str(Path(tmp) / "x.mcap")
        runs = commands(log, args.big)
        if args.only:
            runs = {k: v for k, v in runs.items() if any(o in k for o in args.only)}
        # info reads the log the -w run wrote: make it once first; one run of each
        # command in each tree first, so every module's bytecode is cached
        subprocess.run([sys.executable, "-m", "mbmon", "read", DEMO, "-q", "-w", log], cwd=REPO)
        for cmd in runs.values():
            for root in trees.values():
                cpu_of(cmd, root)
        figures: dict[tuple[str, str], list[tuple[float, float, int]]] = {}
        for _ in range(args.rounds):
            for name, cmd in runs.items():
                for tree, root in trees.items():
                    figures.setdefault((name, tree), []).append(cpu_of(cmd, root))
    head = f"{'run':32s}" + "".join(f" {t + ' CPU ms':>16s} {'wall ms':>9s}" for t in trees)
    if len(trees) == 2:
        head += f" {'saved ms':>9s}"
    print(f"# {args.rounds} rounds, median; load {os.getloadavg()[0]:.1f}")
    print(head)
    for name in runs:
        row = f"{name:32s}"
        med = {}
        for tree in trees:
            got = figures[(name, tree)]
            med[tree] = statistics.median(c for c, _w, _s in got) * 1000
            wall = statistics.median(w for _c, w, _s in got) * 1000
            bad = {s for _c, _w, s in got} - {0}
            row += f" {med[tree]:16.1f} {wall:9.1f}" + (f" exit {sorted(bad)}" if bad else "")
        if len(trees) == 2:
            row += f" {med['against'] - med['this']:9.1f}"
        print(row)
    return 0


if __name__ == "__main__":
    sys.exit(main())
