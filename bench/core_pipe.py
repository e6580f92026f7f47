"""``read`` of a capture on a pipe (``cat F | mbmon read -``) by the compiled core's
streaming entry, next to the core reading the file itself and the pure-Python pipeline
reading the same pipe, in the same run (CPU time of the mbmon child, wall time, peak
RSS).

    python bench/core_pipe.py                     # 1,000,000 ADUs (realistic.py's aligned file)
    python bench/core_pipe.py --adus 200000
    python bench/core_pipe.py --json              # the JSON lines instead of text
    python bench/core_pipe.py --no-pure           # leave the pure pipe run out (it is slow)
    python bench/core_pipe.py --callgrind 100000  # + instructions per ADU (marginal), core

Every run writes to /dev/null. The pipe's writer (``cat``) is a process of its own
whose CPU is not counted (the mbmon child's ``os.wait4`` rusage only); the machine
is shared, so the ratios are by CPU time. The file is bench/realistic.py's (cached
in bench/out/). docs/performance.md records the figures.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))
sys.path.insert(0, str(REPO))
from read_throughput import mbmon_cmd  # noqa: E402
from realistic import capture  # noqa: E402


def _run(cmd: list[str], path: Path, *, pipe: bool, pure: bool) -> tuple[float, float, float, str]:
    """CPU seconds (user + sys), wall seconds and peak RSS (MiB) of the mbmon child of
    ``cmd`` (its input ``path`` through a ``cat`` pipe when ``pipe``), and which path
    ``--debug-core`` said ran."""
    env = dict(os.environ)
    env.pop("MBMON_NO_EXTENSIONS", None)
    if pure:
        env["MBMON_NO_EXTENSIONS"] = "1"
    t0 = time.perf_counter()
    cat = None
    if pipe:
        cat = subprocess.Popen(["cat", str(path)], stdout=subprocess.PIPE)
        child = subprocess.Popen(
            [*cmd, "-", "--debug-core"],
            stdin=cat.stdout,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
        )
        assert cat.stdout is not None
        cat.stdout.close()  # the child holds the pipe's read end
    else:
        child = subprocess.Popen(
            [*cmd, str(path), "--debug-core"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
        )
    assert child.stderr is not None
    err = child.stderr.read().decode(errors="replace")
    _, status, ru = os.wait4(child.pid, 0)
    wall = time.perf_counter() - t0
    if cat is not None:
        cat.wait()
    if os.waitstatus_to_exitcode(status) != 0:
        sys.stderr.write(err[-2000:])
    said = next((ln for ln in err.splitlines() if "core:" in ln), "?").strip()
    return ru.ru_utime + ru.ru_stime, wall, ru.ru_maxrss / 1024, said


def _instructions(cmd: list[str], path: Path, *, pipe: bool) -> int:
    """Callgrind instructions of the mbmon child on ``path`` (read through a pipe from
    a ``cat`` outside valgrind when ``pipe``), every thread."""
    out = path.parent / "core-pipe-callgrind.out"
    grind = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", *cmd]
    env = dict(os.environ)
    env.pop("MBMON_NO_EXTENSIONS", None)
    if pipe:
        with open(path, "rb") as f:
            cat = subprocess.Popen(["cat"], stdin=f, stdout=subprocess.PIPE)
            subprocess.run(
                [*grind, "-"], stdin=cat.stdout, stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL, env=env, check=False,
            )  # fmt: skip
            cat.wait()
    else:
        subprocess.run(
            [*grind, str(path)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            env=env, check=False,
        )  # fmt: skip
    text = out.read_text(errors="replace")
    out.unlink()
    return int(next(ln for ln in text.splitlines() if ln.startswith("summary:")).split()[1])


def callgrind(n: int, cmd: list[str]) -> None:
    """Marginal instructions per ADU, (I(N) - I(N/5)) / (4N/5), the file and the pipe."""
    small = capture("polling", n // 5, 8, 2, "aligned")
    big = capture("polling", n, 8, 2, "aligned")
    for name, pipe in (("core, file", False), ("core, pipe", True)):
        low = _instructions(cmd, small, pipe=pipe)
        high = _instructions(cmd, big, pipe=pipe)
        print(f"  {name:12} {(high - low) / (n - n // 5):8.0f} instructions per ADU (callgrind)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--adus", type=int, default=1_000_000)
    parser.add_argument("--json", action="store_true", help="JSON lines instead of text")
    parser.add_argument("--no-pure", action="store_true", help="skip the pure pipe run")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each (best CPU kept)")
    parser.add_argument("--callgrind", type=int, metavar="N", help="+ instructions per ADU")
    args = parser.parse_args()
    path = capture("polling", args.adus, 8, 2, "aligned")
    cmd = [*mbmon_cmd(), "read", *(["--json"] if args.json else [])]
    runs = [("core, file", False, False), ("core, pipe", True, False)]
    if not args.no_pure:
        runs.append(("pure, pipe", True, True))
    print(f"{path.name}: read{' --json' if args.json else ''}, best of {args.repeat} by CPU")
    best: dict[str, float] = {}
    for name, pipe, pure in runs:
        got = [_run(cmd, path, pipe=pipe, pure=pure) for _ in range(1 if pure else args.repeat)]
        cpu, wall, rss, said = min(got)
        best[name] = cpu
        print(f"  {name:12} {cpu:7.2f} s CPU {wall:7.2f} s wall {rss:6.0f} MiB  ({said})")
    anchor = best["core, file"]
    for name, cpu in best.items():
        print(f"  {name:12} {cpu / anchor:5.2f}x the core's file read")
    if args.callgrind:
        callgrind(args.callgrind, cmd)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
