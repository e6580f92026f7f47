"""A Modbus/TCP capture that takes mbmon seconds to read: the input of the tests that
stop a running ``read`` (signals, kills) and must find it still reading; and the one
loop those tests share: start ``read -w LOG``, wait for the log, wait a while, signal."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from mbmon.io.pcap import PcapWriter, TcpConversation

REPO = Path(__file__).resolve().parents[1]
#: the environment of the ``mbmon`` child processes: this checkout's code, times in UTC
ENV = {**os.environ, "PYTHONPATH": str(REPO), "TZ": "UTC"}

_REQUEST = bytes.fromhex("0000000601030064000A")  # after the tid: read R100..R109
_ANSWER = bytes.fromhex("00000017010314") + bytes(20)


def write_long_capture(path: Path, segments: int) -> Path:
    """``segments`` request segments and their answers, 25 pipelined ADUs each, 1 ms
    apart, on one connection from its handshake."""
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:502")
    ts = 1_700_000_000.0
    with PcapWriter(path) as w:
        for frame in conv.open():
            w.write(ts, frame)
        tid = 0
        for _ in range(segments):
            reqs, resps = [], []
            for _ in range(25):
                tid = (tid + 1) & 0xFFFF
                reqs.append(tid.to_bytes(2, "big") + _REQUEST)
                resps.append(tid.to_bytes(2, "big") + _ANSWER)
            ts += 0.001
            w.write(ts, conv.send(True, b"".join(reqs)))
            ts += 0.001
            w.write(ts, conv.send(False, b"".join(resps)))
    return path


def signal_while_logging(
    capture: Path,
    log: Path,
    sig: signal.Signals,
    delay: float,
    *,
    args: Sequence[str] = (),
    entry: Sequence[str] = ("-m", "mbmon"),
    timeout: float = 120,
    core: bool = False,
) -> tuple[int, str]:
    """Run ``mbmon read CAPTURE ARGS -w LOG``, wait until ``log`` exists (records flow
    from then on), ``delay`` seconds more, then send ``sig``; the exit status and
    stderr once it ended. The read must still be going when the signal is sent (the
    capture must outlast the test: an assertion says so).

    Without ``core`` the pure pipeline reads (``MBMON_NO_EXTENSIONS=1``) and stdout
    is discarded. With it the compiled core reads, which takes the long capture in
    about a second: its console goes to a pipe nobody reads until the end, so the
    run waits there, mid-capture, with the log open (``ARGS`` must not hold
    ``-q``)."""
    env = ENV if core else {**ENV, "MBMON_NO_EXTENSIONS": "1"}
    proc = subprocess.Popen(
        [sys.executable, *entry, "read", str(capture), *args, "-w", str(log)],
        stdout=subprocess.PIPE if core else subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + 60
    while not log.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)  # the log is open: records flow from now on
    time.sleep(delay)
    if proc.poll() is not None:
        _, err = proc.communicate()
        raise AssertionError(f"the input must outlast the test: read ended first\n{err}")
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=timeout)
    return proc.returncode, err
