"""Cost of ``--profile hrss``: ``mbmon read F --profile hrss`` against plain ``mbmon read F``.

    python bench/hrss_session.py                     # 200,000 ADUs, 5 runs each, best of
    python bench/hrss_session.py --adus 50000 --runs 3
    python bench/hrss_session.py --profile           # cProfile of read --profile hrss, in process
    python bench/hrss_session.py --tree /tmp/old     # time another tree (git archive REV | tar -x)

What this script owns: a reproducible (seeded) capture of an HRSS robot cell
as a PLC and an HMI see it, cached in ``bench/out/``, and the timing of both
commands as child processes (stdout to /dev/null, wall time, best of N).
The target: ``--profile hrss`` costs at most 1.5x plain ``read``.

The capture (Ethernet/IPv4/TCP, one ADU per segment, checksums valid, written
with :mod:`mbmon.io.pcap`): a robot at 192.168.0.10:502 (unit 1), two
client connections that were open before the capture started (no handshake):

* a PLC that polls the robot state every cycle (IR200..IR201 status/action,
  IR300..IR311 A1..A6, IR400..IR411 X..C, IR520..IR524 speed/motion,
  IR100..IR102 override/queue; IR500..IR503 errors every tenth cycle) and
  drives commands through R200..R251: PTP and LIN moves written with FC 10
  (R201..R226), executed with R200 = 1, followed until IR200 says success
  (the robot reports Running in IR524 meanwhile), reset with R200 = 0; now and
  then a Get TOOL with its returns read from IR202..IR214, a speed override
  written to R100, a command number written with FC 06 and its parameters with
  FC 10 separately;
* an HMI that polls A1..A6 and X..C.

Joint angles and the pose move toward each target while the robot runs and
jitter by a few thousandths every poll, so register values change on every
poll, as in a real cell.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import pstats
import random
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "bench" / "out"
GEN_VERSION = 1  # bump when the generator changes: the cache key
TARGET_RATIO = 1.5

sys.path.insert(0, str(REPO))
from mbmon.io.pcap import PcapWriter, TcpConversation  # noqa: E402
from mbmon.protocol.pdu import (  # noqa: E402
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
)
from mbmon.semantics.words import split_i32, u16  # noqa: E402

ROBOT = "192.168.0.10:502"
UNIT = 1


def _i32_words(value: int) -> list[int]:
    lo, hi = split_i32(value)
    return [u16(lo), u16(hi)]


@dataclass
class _Robot:
    """The state the robot reports: joints and pose in 0.001 units, status, motion."""

    joints: list[int]
    pose: list[int]
    status: int = 0  # IR200: 0 ready, 1 success, 2 fail
    action: int = 0  # IR201
    motion: int = 1  # IR524: 1 idle, 2 running
    speed: int = 50  # IR100 override %
    queue: int = 0  # IR102
    target: list[int] | None = None
    remaining: int = 0  # polls until the motion ends


class _Capture:
    """Writes transactions (request segment, response segment) on two connections."""

    def __init__(self, path: Path, rng: random.Random) -> None:
        self.rng = rng
        self.out = PcapWriter(path)
        self.ts = 1_700_000_000.0
        self.adus = 0
        self.tids: dict[str, int] = {}
        self.conns = {
            name: TcpConversation(
                client, ROBOT, client_isn=rng.getrandbits(32), server_isn=rng.getrandbits(32)
            )
            for name, client in (("plc", "192.168.0.20:49152"), ("hmi", "192.168.0.30:50211"))
        }

    def tx(self, conn: str, request: bytes, response: bytes) -> None:
        c = self.conns[conn]
        tid = self.tids[conn] = (self.tids.get(conn, self.rng.randrange(0x10000)) + 1) & 0xFFFF
        for from_client, pdu in ((True, request), (False, response)):
            self.ts += self.rng.uniform(0.0002, 0.0012)
            mbap = tid.to_bytes(2, "big") + b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big")
            self.out.write(self.ts, c.send(from_client, mbap + bytes((UNIT,)) + pdu))
            self.adus += 1

    def read(self, conn: str, address: int, values: list[int]) -> None:
        self.tx(conn, encode_read_request(0x04, address, len(values)),
                encode_read_response(0x04, [u16(v) for v in values]))  # fmt: skip

    def write(self, address: int, values: list[int]) -> None:
        vals = [u16(v) for v in values]
        if len(vals) == 1:
            pdu = encode_write_single(0x06, address, vals[0])
            self.tx("plc", pdu, pdu)
        else:
            self.tx("plc", encode_write_multiple_request(0x10, address, vals),
                    encode_write_multiple_response(0x10, address, len(vals)))  # fmt: skip


def _jitter(rng: random.Random, values: list[int]) -> list[int]:
    return [v + rng.randint(-3, 3) for v in values]


def _words32(values: list[int]) -> list[int]:
    return [w for v in values for w in _i32_words(v)]


def _poll(cap: _Capture, robot: _Robot, cycle: int) -> None:
    rng = cap.rng
    if robot.target is not None and robot.remaining > 0:
        robot.remaining -= 1
        robot.joints = [j + (t - j) // (robot.remaining + 1) for j, t in
                        zip(robot.joints, robot.target, strict=True)]  # fmt: skip
        robot.pose = [p + rng.randint(-900, 900) for p in robot.pose]
        if robot.remaining == 0:
            robot.motion, robot.status, robot.target = 1, 1, None
    joints = _jitter(rng, robot.joints)
    pose = _jitter(rng, robot.pose)
    cap.read("plc", 200, [robot.status, robot.action])
    cap.read("plc", 300, _words32(joints))
    cap.read("plc", 400, _words32(pose))
    cap.read("plc", 520, [*_i32_words(rng.randint(0, 250_000)), 1, 200, robot.motion])
    cap.read("plc", 100, [robot.speed, robot.action, robot.queue])
    if cycle % 10 == 0:
        cap.read("plc", 500, [0, 0, 0, 0])
    if cycle % 2 == 0:
        cap.read("hmi", 300, _words32(_jitter(rng, robot.joints)))
        cap.read("hmi", 400, _words32(_jitter(rng, robot.pose)))


def _move(cap: _Capture, robot: _Robot, code: int) -> None:
    rng = cap.rng
    target = [rng.randint(-170_000, 170_000) for _ in range(6)]
    speed, acc, tool, base = rng.choice((10, 30, 50, 100)), 100, rng.randint(0, 3), 0
    params = [code, 0, *_words32(target), speed, acc, tool, base, 0, 0, 0, 0, 0, 0, 0, 0]
    if rng.random() < 0.2:  # command number and parameters in separate requests
        cap.write(201, params[:1])
        cap.write(202, params[1:])
    else:
        cap.write(201, params)
    cap.write(200, [1])
    robot.status, robot.action, robot.motion = 0, code, 2
    robot.target, robot.remaining = target, rng.randint(5, 25)


def _get_tool(cap: _Capture, robot: _Robot) -> None:
    tool = cap.rng.randint(0, 15)
    cap.write(201, [201, tool])
    cap.write(200, [1])
    robot.status, robot.action = 0, 201
    cap.read("plc", 200, [robot.status, robot.action])
    robot.status = 1
    cap.read("plc", 200, [robot.status, robot.action])
    cap.read("plc", 202, [tool, *_words32([cap.rng.randint(-50_000, 50_000) for _ in range(6)])])


def build_capture(adus: int, path: Path, seed: int = 9) -> dict[str, int]:
    """Write a capture of about ``adus`` ADUs; return counts of what it holds."""
    rng = random.Random(seed)
    robot = _Robot(joints=[0, 0, 0, 0, -90_000, 0], pose=[400_000, 0, 600_000, 180_000, 0, 0])
    cap = _Capture(path, rng)
    cycle = commands = 0
    with cap.out:
        while cap.adus < adus:
            cycle += 1
            _poll(cap, robot, cycle)
            idle = robot.target is None
            if idle and robot.status == 1:
                cap.write(200, [0])  # reset before the next command
                robot.status = 0
            elif idle and rng.random() < 0.15:
                commands += 1
                pick = rng.random()
                if pick < 0.1:
                    _get_tool(cap, robot)
                    cap.write(200, [0])
                    robot.status = 0
                elif pick < 0.15:
                    robot.speed = rng.choice((10, 50, 100))
                    cap.write(100, [robot.speed])
                else:
                    _move(cap, robot, rng.choice((0, 0, 1)))
    return {"adus": cap.adus, "cycles": cycle, "commands": commands}


def capture(adus: int) -> Path:
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"hrss_session_{adus}_v{GEN_VERSION}.pcap"
    if not path.exists():
        tmp = path.with_suffix(".tmp")
        t0 = time.perf_counter()
        stats = build_capture(adus, tmp)
        tmp.rename(path)
        print(f"built {path.name}: {stats} in {time.perf_counter() - t0:.1f} s")
    return path


def _env(tree: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(tree) + os.pathsep + env.get("PYTHONPATH", "")  # and cwd=tree: -m
    return env


def timed(cmd: list[str], runs: int, tree: Path = REPO) -> tuple[float, float]:
    """Best wall time and best CPU time (user + sys) of ``runs`` child runs, stdout to /dev/null.

    CPU time is the figure to compare on a loaded machine: other processes
    stretch wall time, not the child's own CPU seconds.
    """
    wall = cpu = float("inf")
    for _ in range(runs):
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, env=_env(tree), cwd=tree)
        _, status, ru = os.wait4(proc.pid, 0)
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, ru.ru_utime + ru.ru_stime)
        if os.waitstatus_to_exitcode(status) != 0:
            raise SystemExit(f"{' '.join(cmd)} failed")
    return wall, cpu


def profile(path: Path, top: int = 30) -> None:
    """cProfile ``mbmon read F --profile hrss`` in this process, output discarded."""
    from mbmon.cli import main

    prof = cProfile.Profile()
    real = sys.stdout
    sys.stdout = io.TextIOWrapper(open(os.devnull, "wb"), encoding="utf-8")
    try:
        prof.runcall(main, ["read", str(path), "--profile", "hrss"])
    finally:
        sys.stdout.close()
        sys.stdout = real
    pstats.Stats(prof).sort_stats("tottime").print_stats(top)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--adus", type=int, default=200_000)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--profile", action="store_true", help="cProfile instead of timing")
    ap.add_argument(
        "--tree",
        type=Path,
        default=REPO,
        help="the mbmon source tree to time (e.g. an unpacked older commit)",
    )
    args = ap.parse_args(argv)
    path = capture(args.adus)
    if args.profile:
        profile(path)
        return 0
    base = [sys.executable, "-m", "mbmon", "read", str(path)]
    print(f"{path.name}: {path.stat().st_size / 1e6:.1f} MB, load {os.getloadavg()[0]:.2f}")
    print(f"  mbmon from {args.tree}")
    plain = timed(base, args.runs, args.tree)
    hrss = timed([*base, "--profile", "hrss"], args.runs, args.tree)
    for name, (wall, cpu) in (("read", plain), ("read --profile hrss", hrss)):
        rate = args.adus / cpu
        print(f"  {name:<20} wall {wall:7.2f} s  cpu {cpu:7.2f} s  {rate:>10,.0f} ADUs/cpu-s")
    ratio = hrss[1] / plain[1]
    verdict = "met" if ratio <= TARGET_RATIO else "NOT met"
    print(
        f"  ratio (cpu) {ratio:.2f}x, (wall) {hrss[0] / plain[0]:.2f}x "
        f"(target <= {TARGET_RATIO}x: {verdict})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
