"""The wiring: ``mbmon --version`` names the active core, ``read --debug-core`` says
which path ran, and ``MBMON_NO_EXTENSIONS=1`` runs the Python pipeline with the same
bytes on stdout and stderr."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from core_diff import ROOT, require_core

DEMO = ROOT / "captures" / "demo.pcap"
RTU = ROOT / "captures" / "sim_rtu.pcap"


def _mbmon(*args: str, pure: bool = False) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ)
    env.pop("MBMON_NO_EXTENSIONS", None)
    if pure:
        env["MBMON_NO_EXTENSIONS"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "mbmon", *args], capture_output=True, env=env, cwd=ROOT,
        timeout=120,
    )  # fmt: skip


def test_version_names_the_core() -> None:
    pure = _mbmon("--version", pure=True)
    assert pure.returncode == 0
    assert b"core: pure Python (MBMON_NO_EXTENSIONS is set)" in pure.stdout
    require_core()
    assert b"core: compiled" in _mbmon("--version").stdout


@pytest.mark.parametrize("fmt", [[], ["--json"]])
def test_read_same_bytes_either_way(fmt: list[str]) -> None:
    require_core()
    fast = _mbmon("read", str(DEMO), "--debug-core", *fmt)
    pure = _mbmon("read", str(DEMO), "--debug-core", *fmt, pure=True)
    assert fast.returncode == pure.returncode == 0
    assert b"core: the compiled core read the input" in fast.stderr
    assert b"core: declined (the compiled core is unavailable" in pure.stderr
    assert fast.stdout == pure.stdout
    assert fast.stderr.splitlines()[1:] == pure.stderr.splitlines()[1:]  # the summary


def test_declines_are_visible_and_change_nothing(tmp_path: Path) -> None:
    require_core()
    rtu = _mbmon("read", str(RTU), "--baud", "9600", "--debug-core")
    assert b"core: declined (--baud on a captured RTU bus" in rtu.stderr
    assert rtu.stdout == _mbmon("read", str(RTU), "--baud", "9600", pure=True).stdout
    for window in ("--before", "--after"):  # the pipeline's usage error, not the core's lines
        alone = _mbmon("read", str(DEMO), window, "5s", "--debug-core")
        assert b"core: declined (" + window.encode() + b" is not covered" in alone.stderr
        assert alone.returncode == 2 and b"needs --trigger" in alone.stderr
        assert alone.stdout == b""
    count = _mbmon("read", str(DEMO), "-c", "3", "-w", str(tmp_path / "x.jsonl"), "--debug-core")
    assert b"core: declined (-w other than one .mcap log is not covered" in count.stderr
    assert len(count.stdout.splitlines()) == 4  # the Connect, then 3 frames (-c counts frames)


def _two_ports(path: Path, other_port: int) -> Path:
    """A capture of two Modbus/TCP connections, one to port 502 and one to
    ``other_port``, interleaved packet by packet."""
    from gen import T0, adus, every_function_pair, write_frames

    from mbmon.io.pcap import TcpConversation

    pairs = every_function_pair()[:6]
    frames: list[bytes] = []
    convs = [
        TcpConversation("10.0.0.1:40000", "10.0.0.2:502"),
        TcpConversation("10.0.0.3:40001", f"10.0.0.4:{other_port}"),
    ]
    for conv in convs:
        frames += conv.open()
    for c, data in adus(pairs):
        frames += [conv.send(c, data) for conv in convs]
    return write_frames(path, [(T0 + i * 0.001, f) for i, f in enumerate(frames)])


def test_port_detection_declines_only_where_it_could_find_something(tmp_path: Path) -> None:
    """Port detection (on by default) may find Modbus on any TCP port: the core
    declines a capture where it does (and reads it with --no-detect)."""
    require_core()
    both = _two_ports(tmp_path / "both.pcap", 1502)
    fast = _mbmon("read", str(both), "--debug-core")
    assert b"core: declined (Modbus found by port detection on a port not named (port 1502))" in (
        fast.stderr
    )
    assert b"found Modbus/TCP on port 1502" in fast.stderr
    pure = _mbmon("read", str(both), pure=True)
    assert fast.stdout == pure.stdout
    assert fast.stdout.count(b"\n") > 12  # both connections' frames
    bare = _mbmon("read", str(both), "--no-detect", "--debug-core")
    assert b"core: the compiled core read the input" in bare.stderr
    assert bare.stdout == _mbmon("read", str(both), "--no-detect", pure=True).stdout
    only502 = _mbmon("read", str(DEMO), "--debug-core")
    assert b"core: the compiled core read the input" in only502.stderr


@pytest.mark.parametrize("fmt", [[], ["--json"]])
def test_the_common_capture_with_its_end_unanswered_is_read_by_the_core(
    tmp_path: Path, fmt: list[str]
) -> None:
    """A capture that starts mid-connection, every request answered but the last ones:
    the core reads it (their 'No response' at the end is mirrored, not declined), with
    the pipeline's bytes on stdout and the same summary."""
    require_core()
    from gen import T0, adus, every_function_pair, write_conversation

    from mbmon.protocol.mbap import encode_adu
    from mbmon.protocol.pdu import encode_read_request

    stream = adus(every_function_pair()) + [
        (True, encode_adu(200 + i, 1, encode_read_request(3, i, 1))) for i in range(3)
    ]
    times = [T0 + 0.02 * i for i in range(len(stream) - 1)] + [T0 + 9.0]
    path = write_conversation(
        tmp_path / "end.pcap", stream, handshake=False, close=None, times=times
    )
    fast = _mbmon("read", str(path), "--debug-core", *fmt)
    pure = _mbmon("read", str(path), "--debug-core", *fmt, pure=True)
    assert fast.returncode == pure.returncode == 0
    assert b"core: the compiled core read the input" in fast.stderr
    assert fast.stdout == pure.stdout
    assert fast.stderr.splitlines()[1:] == pure.stderr.splitlines()[1:]  # the summary
    assert sum(b"No response" in line for line in fast.stdout.splitlines()) == 3
