"""Proxy latency and throughput: FC 03 (10 registers) through several forwarders.

Usage::

    python bench/proxy_latency.py [--seconds 3] [--clients 1 8] [--modbus-proxy PATH]
    python bench/proxy_latency.py --soak 600          # memory of mbmon proxy -w x.mcap

Every party is its own process on 127.0.0.1: a small asyncio Modbus/TCP server
(the upstream: answers every request with 10 registers, some of which change
every poll as a moving robot's positions do; ``--fixed-values`` for the same
answer every time), the forwarder under test, and raw-socket clients (one
process per client, blocking sockets, one request in flight each). Targets:

* ``direct``          clients talk to the upstream itself (the anchor);
* ``bare``            a bare asyncio byte forwarder (one upstream connection per
                      client, bytes forwarded as they arrive, nothing else);
* ``bare buffered``   (``--bare-buffered``) the same forwarder reading into a buffer of
                      its own (``asyncio.BufferedProtocol``), as mbmon's engine does:
                      informational, the targets are against ``bare``;
* ``mbmon``           ``mbmon proxy --quiet``;
* ``mbmon -w mcap``   ``mbmon proxy --quiet -w x.mcap``;
* ``..., observer at normal priority`` (``--normal-priority``) ``mbmon`` and ``mbmon -w
                      mcap`` with ``MBMON_OBSERVE_PRIORITY=normal``: the observing process
                      at the priority it started with instead of idle (what yielding to
                      the forwarding is worth, in the same run);
* ``mbmon, observer stopped`` (``--observer-stopped``) ``mbmon proxy --quiet`` with its
                      observing process stopped (``SIGSTOP``) and its backlog full, so
                      the forwarding process forwards without a copy: the forwarding
                      alone, on the cores the observer would use. Informational: it
                      shows what observing costs, not a way to run mbmon;
* ``floor ...``       (``--floor-observers``) mbmon's forwarding process with the least
                      observer any Python code could be in place of the hub
                      (``bench/proxy_floor.py``): its three stages through the pipe, the
                      last two also ``inline`` in the forwarding loop. A lower bound of
                      what observing costs, to judge the targets by. Informational;
* ``modbus-proxy``    the PyPI ``modbus-proxy`` package, when importable (install
                      it, or give ``--modbus-proxy DIR`` with its module).

Printed side by side: requests/s, p50 and p99 round-trip latency, the latency
each forwarder adds over ``direct`` (p50), that added latency as a ratio of the
bare forwarder's, throughput as ratios of the bare forwarder's and
modbus-proxy's, and the forwarder's CPU per request (its process and child
processes, user + system, over the middle of the run: the steadiest figure on
a shared machine), and how long the forwarder stayed busy after its clients
stopped (``lag s``: mbmon's observer may run behind the forwarding within its
backlog; a row marked ``*`` ran faster than it can sustain, measure it longer).
Every target is warmed up first (:func:`warm_up`). ``--anchor DIR`` adds ``mbmon@anchor`` and
``mbmon -w mcap@anchor``: mbmon from another source tree (``git archive main |
tar -x -C DIR``), run next to this tree's in the same minutes.

The targets: added p50 at most 1.5x the bare
forwarder's (with and without -w x.mcap); with 8 clients, throughput at least
2.5x modbus-proxy's and at least 0.8x the bare forwarder's; memory flat over a
10-minute soak. The figures are for the machine they ran on: compare ratios.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import re
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}
sys.path.insert(0, str(ROOT))
from mbmon.proxy.config import MAX_BACKLOG, OBSERVE_PRIORITY_ENV  # noqa: E402
from mbmon.proxy.remote import CHUNK_HEAD, PIPE_SIZE  # noqa: E402

UPSTREAM = r"""
import asyncio, random, struct, sys
FIXED = sys.argv[1:] == ["fixed"]
BODY = bytes([3, 20]) + bytes(range(20))
REGS = struct.Struct(">2B10H").pack
class P(asyncio.Protocol):
    def connection_made(self, t):
        self.t = t
        self.buf = b""
        self.poll = random.randrange(0x10000)  # each connection its own robot: no repeats
    def data_received(self, data):
        buf = self.buf + data
        out = []
        while len(buf) >= 7:
            n = 6 + ((buf[4] << 8) | buf[5])
            if len(buf) < n:
                break
            if FIXED:
                body = BODY
            else:  # a robot's registers: positions move every poll, the rest stays
                c = self.poll = (self.poll + 1) & 0xFFFF
                body = REGS(3, 20, c, c ^ 0x5A5A, (c * 7) & 0xFFFF, c >> 4, 1, 0, 0, 2, 30, 500)
            out.append(buf[:2] + b"\0\0\0\x17" + buf[6:7] + body)
            buf = buf[n:]
        self.buf = buf
        if out:
            self.t.write(b"".join(out))
async def main():
    loop = asyncio.get_running_loop()
    srv = await loop.create_server(P, "127.0.0.1", 0)
    print(srv.sockets[0].getsockname()[1], flush=True)
    await srv.serve_forever()
asyncio.run(main())
"""

BARE = r"""
import asyncio, sys
up_port = int(sys.argv[1])
class Up(asyncio.Protocol):
    def __init__(self, client):
        self.client = client
    def connection_made(self, t):
        self.t = t
    def data_received(self, data):
        self.client.write(data)
    def connection_lost(self, exc):
        self.client.close()
class Client(asyncio.Protocol):
    def connection_made(self, t):
        self.t = t
        self.up = None
        self.pending = []
        asyncio.get_running_loop().create_task(self.connect())
    async def connect(self):
        loop = asyncio.get_running_loop()
        _, self.up = await loop.create_connection(lambda: Up(self.t), "127.0.0.1", up_port)
        for d in self.pending:
            self.up.t.write(d)
    def data_received(self, data):
        if self.up is None:
            self.pending.append(data)
        else:
            self.up.t.write(data)
    def connection_lost(self, exc):
        if self.up is not None:
            self.up.t.close()
async def main():
    loop = asyncio.get_running_loop()
    srv = await loop.create_server(Client, "127.0.0.1", 0)
    print(srv.sockets[0].getsockname()[1], flush=True)
    await srv.serve_forever()
asyncio.run(main())
"""

#: The same forwarder reading into a buffer of its own (asyncio.BufferedProtocol), as
#: mbmon's engine does; plain asyncio protocols get a new 256 KiB bytes object per read
#: (mmap + mremap + munmap with glibc's default threshold). Informational (--bare-buffered):
#: the targets' anchor is the plain forwarder above.
BARE_BUFFERED = BARE.replace(
    "class Up(asyncio.Protocol):",
    "BUF = memoryview(bytearray(65536))\n"
    "class Reader(asyncio.BufferedProtocol):\n"
    "    def get_buffer(self, hint):\n"
    "        return BUF\n"
    "    def buffer_updated(self, n):\n"
    "        self.data_received(bytes(BUF[:n]))\n"
    "class Up(Reader):",
).replace("class Client(asyncio.Protocol):", "class Client(Reader):")

#: An anchor's best case: the same code on uvloop, as mbmon's forwarding process runs
#: (``--uvloop-anchors``; asyncio.run takes the installed policy's loop).
UVLOOP = "import uvloop; uvloop.install()\n"

REQUEST = struct.pack(">HHHBBHH", 0, 0, 6, 1, 3, 0, 10)


def _spawn_printing_port(args: list[str], env: dict[str, str] | None = None) -> tuple[Any, int]:
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    port = int(proc.stdout.readline())
    return proc, port


def _wait_port(port: int, timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"nothing listens on {port}")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _stop(proc: Any, sig: int = signal.SIGTERM) -> None:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextmanager
def upstream(fixed: bool = False) -> Iterator[int]:
    """The upstream server: its answers' register values change every poll, as a
    moving robot's do (``fixed``: the same 10 values in every answer)."""
    proc, port = _spawn_printing_port(
        [sys.executable, "-c", UPSTREAM, *(["fixed"] if fixed else [])]
    )
    try:
        yield port
    finally:
        _stop(proc)


@contextmanager
def target(
    name: str,
    up: int,
    tmp: Path,
    mp_path: str | None,
    trees: dict[str, str] | None = None,
    seen: dict[str, float] | None = None,
) -> Iterator[tuple[int, int | None]]:
    """Start the forwarder ``name`` in front of ``up``; yield (port, pid). For mbmon,
    ``seen["observed"]`` is then the share of the chunks it forwarded that its
    observer took (its summary's "not observed" count: the rest were dropped
    because the observer fell behind its backlog).

    ``mbmon ... @LABEL`` runs mbmon from the source tree ``trees[LABEL]`` (an anchor:
    another commit's code, alternated with this tree's in the same run)."""
    if name == "direct":
        yield up, None
        return
    if name == "bare":
        proc, port = _spawn_printing_port([sys.executable, "-c", BARE, str(up)])
    elif name == "bare buffered":
        proc, port = _spawn_printing_port([sys.executable, "-c", BARE_BUFFERED, str(up)])
    elif name == "bare buffered uvloop":
        proc, port = _spawn_printing_port([sys.executable, "-c", UVLOOP + BARE_BUFFERED, str(up)])
    elif name.startswith(("mbmon", FLOOR)):
        if name.startswith(FLOOR):
            stage, *how = FLOOR_STAGES[name].split()
            args = [sys.executable, str(ROOT / "bench" / "proxy_floor.py"), stage, *how,
                    "--upstream", f"127.0.0.1:{up}"]  # fmt: skip
            if stage == "log":
                args += ["-w", str(tmp / f"floor-{time.monotonic_ns()}.jsonl")]
        else:
            args = [sys.executable, "-m", "mbmon", "proxy", "--upstream", f"127.0.0.1:{up}",
                    "--listen", "127.0.0.1:0", "--quiet"]  # fmt: skip
            if "mcap" in name:
                args += ["-w", str(tmp / f"bench-{time.monotonic_ns()}.mcap")]
        env = ENV
        if "@" in name:
            env = {**os.environ, "PYTHONPATH": (trees or {})[name.split("@", 1)[1]]}
        if NORMAL_PRIORITY in name:  # the observing process at the priority it started with
            env = {**env, OBSERVE_PRIORITY_ENV: "normal"}
        # cwd: not a source tree, whose mbmon ``-m`` would import before PYTHONPATH's
        proc = subprocess.Popen(args, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp)
        assert proc.stderr is not None
        line = proc.stderr.readline()
        m = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
        if not m:
            raise RuntimeError(f"mbmon proxy did not start: {line}")
        port = int(m.group(1))
    elif name.startswith("modbus-proxy"):
        port = _free_port()
        env = dict(os.environ)
        if mp_path:
            env["PYTHONPATH"] = mp_path
        run = ["-m", "modbus_proxy"]
        if name.endswith("uvloop"):  # its own main(), on uvloop
            run = ["-c", UVLOOP + "import sys, modbus_proxy; sys.argv[0] = 'modbus-proxy'; "
                   "modbus_proxy.main()"]  # fmt: skip
        proc = subprocess.Popen(
            [
                sys.executable,
                *run,
                "-b",
                f"tcp://127.0.0.1:{port}",
                "--modbus",
                f"tcp://127.0.0.1:{up}",
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        _wait_port(port)
    else:
        raise ValueError(name)
    try:
        yield port, proc.pid
    finally:
        observing = name.startswith(("mbmon", FLOOR))
        _stop(proc, signal.SIGINT if observing else signal.SIGTERM)
        if observing and proc.stderr is not None:
            summary = proc.stderr.read()
            if os.environ.get("BENCH_VERBOSE"):
                print(f"[{name}] " + summary.strip().replace("\n", f"\n[{name}] "))
            if seen is not None:
                seen["observed"] = observed_share(summary)


def observed_share(summary: str) -> float:
    """The share of forwarded chunks (two a request) that mbmon's observer took, from
    ``mbmon proxy``'s summary (1.0 when it says nothing was left unobserved)."""
    requests = re.search(r"requests (\d+), responses (\d+)", summary)
    dropped = re.search(r"not observed \(monitor behind\) (\d+)", summary)
    if requests is None or dropped is None:
        return 1.0
    chunks = int(requests.group(1)) + int(requests.group(2))
    return max(0.0, 1.0 - int(dropped.group(1)) / chunks) if chunks else 1.0


def _tree_cpu(pid: int) -> float:
    """CPU seconds (user + system) used so far by ``pid`` and its child processes."""
    tck = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for p in _tree(pid):
        try:
            stat = Path(f"/proc/{p}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        total += (int(fields[11]) + int(fields[12])) / tck
    return total


def _client(port: int, seconds: float, start_at: float, queue: Any) -> None:
    """One client process: requests back to back for ``seconds``; latencies in µs."""
    s = socket.create_connection(("127.0.0.1", port))
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    recv, send = s.recv, s.sendall
    perf = time.perf_counter
    lat: list[float] = []
    for _ in range(50):  # warm up (connection set-up upstream, caches)
        send(REQUEST)
        got = 0
        while got < 29:
            got += len(recv(64))
    while time.time() < start_at:
        time.sleep(0.001)
    tid = 0
    end = perf() + seconds
    while True:
        t0 = perf()
        if t0 >= end:
            break
        tid = (tid + 1) & 0xFFFF
        send(struct.pack(">H", tid) + REQUEST[2:])
        got = 0
        while got < 29:
            chunk = recv(64)
            if not chunk:
                raise ConnectionError("closed")
            got += len(chunk)
        lat.append((perf() - t0) * 1e6)
    s.close()
    queue.put(lat)


def measure(port: int, clients: int, seconds: float, pid: int | None = None) -> dict[str, float]:
    """Run ``clients`` client processes for ``seconds``: req/s, p50, p99 and, with the
    forwarder's ``pid``, its CPU (process and children) per request over the run's middle."""
    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    start_at = time.time() + 0.5 + 0.05 * clients
    procs = [
        ctx.Process(target=_client, args=(port, seconds, start_at, queue)) for _ in range(clients)
    ]
    for p in procs:
        p.start()
    cpu = float("nan")
    if pid is not None:
        margin = min(0.5, seconds / 5)
        time.sleep(max(0.0, start_at + margin - time.time()))
        c0, t0 = _tree_cpu(pid), time.time()
        time.sleep(max(0.0, start_at + seconds - margin - time.time()))
        cpu_s, window = _tree_cpu(pid) - c0, time.time() - t0
    lats: list[float] = []
    for _ in procs:
        lats.extend(queue.get(timeout=seconds + 60))
    for p in procs:
        p.join()
    lag = catch_up(pid) if pid is not None else 0.0
    lats.sort()
    n = len(lats)
    if pid is not None and n:
        cpu = cpu_s / (n / seconds * window) * 1e6
    return {
        "rps": n / seconds,
        "p50": lats[n // 2],
        "p99": lats[min(n - 1, int(n * 0.99))],
        "n": n,
        "cpu": cpu,
        "lag": lag,
    }


def catch_up(pid: int, limit: float = 30.0) -> float:
    """Seconds the forwarder ``pid`` (its process tree) stays busy after the clients
    stopped: work it put off during the run (mbmon's observer decoding and logging
    behind the forwarding, within its backlog). A run whose forwarder needed that
    long after it ran faster than the forwarder can sustain: a row with more than
    :data:`LAG_OK` is marked ``*`` (measure longer, or read it as a bound)."""
    t0 = time.monotonic()
    last = _tree_cpu(pid)
    while time.monotonic() - t0 < limit:
        time.sleep(0.1)
        now = _tree_cpu(pid)
        if now - last < 0.02:  # under a fifth of a core: idle but for its timers
            return max(0.0, time.monotonic() - t0 - 0.1)
        last = now
    return limit


#: catch-up time (s) that is only the observer's last hand-overs and log flush (every 0.5 s)
LAG_OK = 0.8

#: The rows of mbmon with its observing process at normal priority (``--normal-priority``).
NORMAL_PRIORITY = ", observer at normal priority"

#: The informational row of mbmon's forwarding alone (``--observer-stopped``).
OBSERVER_STOPPED = "mbmon, observer stopped"

#: The informational rows of mbmon's forwarding with the least observer any Python
#: code could be (``--floor-observers``; bench/proxy_floor.py), by the floor's stage.
FLOOR = "floor"
FLOOR_STAGES = {
    "floor: copies only": "copies",
    "floor: + decode, pairing": "decode",
    "floor: + a JSON line/ADU": "log",
    "floor inline: + decode, pairing": "decode --inline",
    "floor inline: + a JSON line/ADU": "log --inline",
}

#: Requests that certainly fill a stopped observer's backlog: mbmon's forwarding
#: process keeps up to MAX_BACKLOG items (two a request) for its observer, behind what
#: its pipe holds (PIPE_SIZE bytes, a 16-byte head and 12 bytes or more a chunk);
#: past that it forwards without a copy. A quarter more, for certain.
BACKLOG_FILL = (MAX_BACKLOG + PIPE_SIZE // (CHUNK_HEAD.size + len(REQUEST))) // 2 * 5 // 4


def stop_observer(pid: int, port: int, clients: int) -> None:
    """Stop mbmon's observing process ``pid`` (the parent; the forwarding runs in its
    child) and run clients through ``port`` until its backlog is full: from then on
    the forwarding process forwards without a copy, as it does whenever its observer
    falls that far behind. The caller sends ``SIGCONT`` after the measured run."""
    os.kill(pid, signal.SIGSTOP)
    sent = 0
    while sent < BACKLOG_FILL:
        sent += int(measure(port, clients, 1.0)["n"])


def warm_up(port: int, clients: int) -> None:
    """Run ``clients`` clients for a moment and let them close, before a measured run.

    Every party is a fresh process, and a fresh CPython process that reads with
    ``sock.recv(256 KiB)`` (asyncio's plain ``Protocol`` transports: the bare
    forwarder, the upstream) gets each such buffer from ``mmap`` and gives it
    back with ``mremap``/``munmap``, three system calls a read, until glibc's
    malloc raises its mmap threshold: on the first free of such a buffer whole,
    which happens when a read finds nothing (a connection closing). Measured
    cold, the bare forwarder ran at half its speed (25,000 against 53,000
    req/s at 8 clients); warm is how a forwarder that has served a while runs,
    and its best case. ``--cold`` measures without."""
    measure(port, clients, 0.3)


def _has_modbus_proxy(path: str | None) -> bool:
    env = dict(os.environ)
    if path:
        env["PYTHONPATH"] = path
    r = subprocess.run([sys.executable, "-c", "import modbus_proxy"], env=env, capture_output=True)
    return r.returncode == 0


def bench(args: argparse.Namespace) -> None:
    names = ["direct", "bare", "mbmon", "mbmon -w mcap"]
    trees: dict[str, str] = {}
    if args.anchor:
        trees["anchor"] = args.anchor
        names[2:2] = ["mbmon@anchor"]
        names[4:4] = ["mbmon -w mcap@anchor"]
    if args.bare_buffered:
        names.insert(2, "bare buffered")
    if args.uvloop_anchors:
        names.insert(names.index("mbmon"), "bare buffered uvloop")
    if args.normal_priority:
        names.insert(names.index("mbmon") + 1, "mbmon" + NORMAL_PRIORITY)
        names.insert(names.index("mbmon -w mcap") + 1, "mbmon -w mcap" + NORMAL_PRIORITY)
    if args.observer_stopped:
        names.insert(names.index("mbmon"), OBSERVER_STOPPED)
    if args.floor_observers:
        at = names.index("mbmon")
        names[at:at] = list(FLOOR_STAGES)
    if _has_modbus_proxy(args.modbus_proxy):
        names.append("modbus-proxy")
        if args.uvloop_anchors:
            names.append("modbus-proxy uvloop")
    else:
        print("modbus-proxy: not importable (pip install modbus-proxy, or --modbus-proxy DIR)")
    runs: dict[tuple[str, int], list[dict[str, float]]] = {}
    with tempfile.TemporaryDirectory() as tmp, upstream(args.fixed_values) as up:
        for round_ in range(args.rounds):
            for clients in args.clients:
                # every other round the other way round: no target always runs first
                for name in names if round_ % 2 == 0 else names[::-1]:
                    seen: dict[str, float] = {}
                    with target(name, up, Path(tmp), args.modbus_proxy, trees, seen) as (
                        port,
                        pid,
                    ):
                        if not args.cold:
                            warm_up(port, clients)
                        stopped = name == OBSERVER_STOPPED and pid is not None
                        if stopped:
                            stop_observer(pid, port, clients)
                        try:
                            run = measure(port, clients, args.seconds, pid)
                        finally:
                            if stopped:
                                os.kill(pid, signal.SIGCONT)
                    run["observed"] = seen.get("observed", 1.0)
                    runs.setdefault((name, clients), []).append(run)
    # each figure is the median over the rounds (one round: the figure itself)
    results = {
        key: {k: statistics.median(r[k] for r in rs) for k in rs[0]} for key, rs in runs.items()
    }
    load = os.getloadavg()
    rounds = f", median of {args.rounds} alternated rounds" if args.rounds > 1 else ""
    values = "the same values every poll" if args.fixed_values else "values change every poll"
    print(f"\nFC 03 x 10 registers ({values}), {args.seconds:g} s per run{rounds}, "
          f"{os.cpu_count()} CPUs, "
          f"load {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")  # fmt: skip
    w = max(20, *(len(name) for name in names))
    head = (f"{'target':<{w}} {'clients':>7} {'req/s':>8} {'p50 us':>8} {'p99 us':>8} "
            f"{'added p50':>9} {'x bare':>7} {'rps/bare':>8} {'rps/m-p':>8} "
            f"{'cpu us/req':>10} {'lag s':>6} {'obs %':>6}")  # fmt: skip
    print(head)
    print("-" * len(head))
    for clients in args.clients:
        direct = results[("direct", clients)]
        bare = results[("bare", clients)]
        bare_added = bare["p50"] - direct["p50"]
        mproxy = results.get(("modbus-proxy", clients))
        for name in names:
            r = results[(name, clients)]
            added = r["p50"] - direct["p50"]
            x_bare = f"{added / bare_added:.2f}" if name != "direct" and bare_added > 0 else "-"
            rps_bare = f"{r['rps'] / bare['rps']:.2f}"
            rps_mp = f"{r['rps'] / mproxy['rps']:.2f}" if mproxy else "-"
            cpu = "-" if r["cpu"] != r["cpu"] else f"{r['cpu']:.0f}"
            judged = name != OBSERVER_STOPPED  # that row's observer is stopped on purpose
            lag = f"{r['lag']:.1f}" + ("*" if judged and r["lag"] > LAG_OK else " ")
            seen = f"{100 * r['observed']:.0f}" + ("*" if judged and r["observed"] < 1 else " ")
            print(f"{name:<{w}} {clients:>7} {r['rps']:>8.0f} {r['p50']:>8.0f} {r['p99']:>8.0f} "
                  f"{added:>9.0f} {x_bare:>7} {rps_bare:>8} {rps_mp:>8} {cpu:>10} "
                  f"{lag:>6} {seen:>6}")  # fmt: skip
    if any(
        r["lag"] > LAG_OK or r["observed"] < 1.0
        for (name, _), r in results.items()
        if name != OBSERVER_STOPPED
    ):
        print(
            f"* busy for more than {LAG_OK} s after its clients stopped, or forwarded chunks "
            "its observer dropped (obs %: the share it observed): the observer ran behind "
            "the forwarding, so req/s is forwarding the observer did not sustain; measure "
            "longer (--seconds 60) and read req/s x obs % as the rate observed in full"
        )
    if args.floor_observers:
        print(
            "floor: mbmon's forwarding process with the least observer any Python code "
            "could be in place of the hub (bench/proxy_floor.py): copies only; + MBAP "
            "framing, decode_pdu and pairing; + one JSON line per ADU to a file. floor "
            "inline: the same observer in the forwarding process's own loop (no copy). A "
            "lower bound of what observing costs, informational"
        )
    if OBSERVER_STOPPED in names:
        print(
            f"{OBSERVER_STOPPED}: mbmon's forwarding process alone (its observer stopped, "
            "its backlog full, chunks forwarded without a copy; obs % counts the run's "
            "whole life): what observing costs on these cores. Informational, not a way to "
            "run mbmon"
        )


def _rss_kib(pid: int) -> int:
    """Resident memory of ``pid`` and its child processes (mbmon proxy forwards in one)."""
    total = 0
    for p in _tree(pid):
        try:
            lines = Path(f"/proc/{p}/status").read_text().splitlines()
        except OSError:
            continue
        total += sum(int(line.split()[1]) for line in lines if line.startswith("VmRSS:"))
    return total


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            ppid = int(stat[stat.rindex(")") + 2 :].split()[1])
            children.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out


def soak(args: argparse.Namespace) -> None:
    """8 clients through ``mbmon proxy -w x.mcap`` (or ``--soak-target``) for ``--soak``
    seconds; RSS samples."""
    with tempfile.TemporaryDirectory() as tmp, upstream(args.fixed_values) as up:
        seen: dict[str, float] = {}
        with target(args.soak_target, up, Path(tmp), None, None, seen) as (port, pid):
            assert pid is not None
            ctx = mp.get_context("fork")
            queue = ctx.Queue()
            procs = [ctx.Process(target=_client, args=(port, args.soak, time.time() + 1, queue))
                     for _ in range(8)]  # fmt: skip
            for p in procs:
                p.start()
            samples = []
            step = max(1.0, args.soak / 20)
            t0 = time.monotonic()
            while time.monotonic() - t0 < args.soak + 1:
                time.sleep(step)
                samples.append((time.monotonic() - t0, _rss_kib(pid)))
                print(f"{samples[-1][0]:7.0f} s  RSS {samples[-1][1] / 1024:7.1f} MiB", flush=True)
            total = sum(len(queue.get(timeout=120)) for _ in procs)
            for p in procs:
                p.join()
    first = statistics.mean(s[1] for s in samples[1:4]) if len(samples) > 4 else samples[0][1]
    last = statistics.mean(s[1] for s in samples[-3:])
    growth = (last - first) / 1024
    load = os.getloadavg()
    rate = total / args.soak
    print(f"{args.soak_target}: {total} requests in {args.soak:g} s ({rate:.0f} req/s); "
          f"RSS {first / 1024:.1f} -> {last / 1024:.1f} MiB ({growth:+.1f} MiB); "
          f"load {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}; observed "
          f"{100 * seen.get('observed', 1.0):.1f} % of the chunks forwarded")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="per run (default 3)")
    parser.add_argument("--clients", type=int, nargs="+", default=[1, 8])
    parser.add_argument(
        "--rounds",
        type=int,
        default=1,
        help="run every target this many times, alternating the order; print medians",
    )
    parser.add_argument("--modbus-proxy", metavar="DIR", help="directory holding modbus_proxy.py")
    parser.add_argument(
        "--bare-buffered",
        action="store_true",
        help="also run the bare forwarder reading into its own buffer (informational)",
    )
    parser.add_argument(
        "--uvloop-anchors",
        action="store_true",
        help="also run the buffered bare forwarder and modbus-proxy on uvloop (the "
        "loop mbmon's forwarding process uses): the anchors' best case, informational",
    )
    parser.add_argument(
        "--anchor",
        metavar="DIR",
        help="also run mbmon from this source tree (e.g. an export of main), next to "
        "this tree's, in the same run: before/after in the same minutes",
    )
    parser.add_argument(
        "--observer-stopped",
        action="store_true",
        help="also run mbmon with its observing process stopped (SIGSTOP) once its "
        "backlog is full: the forwarding alone, without the observation's CPU "
        "(informational: what observing costs)",
    )
    parser.add_argument(
        "--normal-priority",
        action="store_true",
        help="also run mbmon and mbmon -w mcap with the observing process at the priority "
        "it started with (MBMON_OBSERVE_PRIORITY=normal) instead of idle: what yielding "
        "to the forwarding is worth, in the same run",
    )
    parser.add_argument(
        "--floor-observers",
        action="store_true",
        help="also run mbmon's forwarding with the least observer any Python code could "
        "be (bench/proxy_floor.py: three stages through the pipe, two inline): how little "
        "observing can cost "
        "(informational)",
    )
    parser.add_argument(
        "--fixed-values",
        action="store_true",
        help="the upstream answers the same 10 register values every time (the "
        "figures before the benchmark was corrected were measured so); default: values that change "
        "every poll, as a moving robot's positions do",
    )
    parser.add_argument(
        "--cold",
        action="store_true",
        help="measure each target right after it starts, without the warm-up run (see "
        "warm_up: plain asyncio forwarders then run at half speed; before the eighth "
        "session, every figure was measured so)",
    )
    parser.add_argument("--soak", type=float, metavar="S", help="memory soak of S seconds instead")
    parser.add_argument(
        "--soak-target",
        choices=("mbmon", "mbmon -w mcap"),
        default="mbmon -w mcap",
        help="what the soak runs (default: mbmon -w mcap)",
    )
    args = parser.parse_args()
    if args.soak:
        soak(args)
    else:
        bench(args)


if __name__ == "__main__":
    main()
