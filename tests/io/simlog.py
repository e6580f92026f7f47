"""Helpers of the replay-against-servers tests: logs recorded from ``mbmon sim`` through
``mbmon proxy -w`` (real subprocess, real sockets), and ``mbmon replay`` run as a subprocess.

Traffic functions take a connected pymodbus client and return what it got, one entry
per request (registers, bits, or the exception code), so two runs can be compared.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}

Traffic = Callable[[Any], list[Any]]


def result(rr: Any) -> Any:
    """What a pymodbus answer carried: ``("exc", code)``, registers, or bits."""
    if rr.isError():
        return ("exc", getattr(rr, "exception_code", None))
    if getattr(rr, "registers", None):
        return ("regs", list(rr.registers))
    return ("bits", list(rr.bits))


def reads(c: Any) -> list[Any]:
    """Reads that a fresh sim answers the same every time, and three refusals."""
    return [
        result(c.read_holding_registers(100, count=1)),  # speed 100 %
        result(c.read_holding_registers(201, count=10)),
        result(c.read_coils(0, count=16)),
        result(c.read_discrete_inputs(0, count=16)),
        result(c.read_input_registers(0, count=8)),
        result(c.read_input_registers(200, count=2)),
        result(c.read_input_registers(300, count=12)),  # A1..A6
        result(c.read_holding_registers(1949, count=5)),  # exception 02
        result(c.report_device_id()),  # exception 01
        result(c.read_holding_registers(100, count=1, device_id=2)),  # another unit: 0x0B
    ]


def writes_then_reads(c: Any) -> list[Any]:
    """Reads before and after writes of holding registers and coils."""
    return [
        result(c.read_holding_registers(300, count=2)),
        result(c.write_registers(201, [1, 2, 3])),
        result(c.read_holding_registers(201, count=5)),
        result(c.write_register(300, 42)),
        result(c.read_holding_registers(300, count=2)),
        result(c.read_coils(0, count=10)),
        result(c.write_coil(3, True)),
        result(c.read_coils(0, count=10)),
        result(c.write_coils(4, [True, False, True])),
        result(c.read_coils(0, count=10)),
    ]


def program(c: Any) -> list[Any]:
    """The manual's 5.4.5.2 program with LIN, Set/Get PR and JOG (``mbmon.sim.run_program``):
    every request as (function, address, values, what came back), polls included."""
    from mbmon.sim.program import run_program

    result = run_program(client=c, unit=1, poll=0.05, timeout=10.0, jog_seconds=0.3)
    return [(s.function, s.address, s.values, s.result) for s in result.steps]


def client(port: int) -> Any:
    from pymodbus.client import ModbusTcpClient

    c = ModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
    assert c.connect(), f"cannot connect to 127.0.0.1:{port}"
    return c


def run_traffic(port: int, traffic: Traffic) -> list[Any]:
    c = client(port)
    try:
        return traffic(c)
    finally:
        c.close()


def record(sim_port: int, log: Path, traffic: Traffic) -> list[Any]:
    """Run ``traffic`` through ``mbmon proxy -w log`` in front of the sim; what it got."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "proxy", "--upstream", f"127.0.0.1:{sim_port}",
         "--listen", "127.0.0.1:0", "--quiet", "-w", str(log)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV,
    )  # fmt: skip
    assert proc.stderr is not None
    line = proc.stderr.readline()
    m = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
    assert m, f"proxy did not start: {line}{proc.stderr.read()}"
    try:
        got = run_traffic(int(m.group(1)), traffic)
    finally:
        proc.send_signal(signal.SIGINT)
        _out, rest = proc.communicate(timeout=30)
    assert proc.returncode == 0, rest
    return got


class Served:
    """``mbmon replay LOG --serve 127.0.0.1:0 ...`` as a subprocess."""

    def __init__(self, log: Path, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "replay", str(log), "--serve", "127.0.0.1:0", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
        )  # fmt: skip
        assert self.proc.stderr is not None
        self.first = self.proc.stderr.readline()
        m = re.search(r"on 127\.0\.0\.1:(\d+)", self.first)
        if m is None:
            self.proc.kill()
            raise AssertionError(
                f"replay --serve did not start: {self.first}{self.proc.stderr.read()}"
            )
        self.port = int(m.group(1))
        self.err: list[str] = [self.first]
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.err.append(line)

    def stop(self, sig: int = signal.SIGINT) -> tuple[int, str]:
        """End it with ``sig``; exit status and everything it said on stderr."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        code = self.proc.wait(timeout=20)
        self._reader.join(5)
        return code, "".join(self.err)


@contextmanager
def served(log: Path, *args: str) -> Iterator[Served]:
    s = Served(log, *args)
    try:
        yield s
    finally:
        if s.proc.poll() is None:
            s.stop()


def replay(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """``python -m mbmon replay ARGS`` to the end."""
    return subprocess.run(
        [sys.executable, "-m", "mbmon", "replay", *args],
        capture_output=True, text=True, env=ENV, timeout=timeout,
    )  # fmt: skip
