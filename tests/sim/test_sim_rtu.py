"""SimServer as a Modbus RTU slave on a real pty pair made by socat.

The §5.4.5.2 program runs through a pymodbus serial client on the other end of
the pair; a request for another unit must stay unanswered (another slave on the
bus would answer it), a broadcast is executed without an answer, and the bytes
on the line must frame with mbmon's own RTU decoder (CRC checked).
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator

import pytest
from socat_ptys import pty_pair as socat_pty_pair

from mbmon.model import Chunk, Direction, RecordKind, Stream, Transport
from mbmon.pipeline import Pipeline
from mbmon.sim.program import run_program
from mbmon.sim.server import SimServer

pytestmark = pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")

BAUD = 115200


@pytest.fixture
def pty_pair() -> Iterator[tuple[str, str]]:
    with socat_pty_pair() as ends:
        yield ends


def test_the_program_over_rtu_reaches_a1_90(pty_pair: tuple[str, str]) -> None:
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    server_pty, client_pty = pty_pair  # (a pty refuses parity settings: EINVAL, so 8N1)
    packets: list[tuple[float, bytes]] = []
    server = SimServer(
        serial=server_pty,
        baudrate=BAUD,
        parity="N",
        unit=3,
        on_packet=lambda sending, data: packets.append((time.time(), data)),
    )
    assert server.start() == server_pty
    try:
        client = ModbusSerialClient(
            client_pty, framer=FramerType.RTU, baudrate=BAUD, parity="N", timeout=0.5, retries=0
        )
        assert client.connect()
        try:
            result = run_program(client=client, unit=3, jog_seconds=0.2)
            assert result.joints == (90, 0, 0, 0, 0, 0)
            assert result.statuses == {"LIN": 1, "Set PR": 1, "Get PR": 1, "JOG": 1}
            # unit 4 is another slave: no answer at all
            quiet = len(packets)
            with pytest.raises(Exception):  # noqa: B017 - pymodbus raises ModbusIOException
                rr = client.read_input_registers(100, count=1, device_id=4)
                if rr.isError():
                    raise RuntimeError(rr)
            assert len(packets) == quiet + 1  # the request came in, nothing went out
            # a broadcast (unit 0) is executed and not answered
            with pytest.raises(Exception):  # noqa: B017 - no answer to wait for
                rr = client.write_register(100, 50, device_id=0)
                if rr.isError():
                    raise RuntimeError(rr)
            assert len(packets) == quiet + 2
            assert server.snapshot()["speed_pct"] == 50
        finally:
            client.close()
    finally:
        server.stop()
    assert server.snapshot()["joints"][0] >= 90

    # the line's bytes, as one RTU bus stream, frame with CRC and no noise
    stream = Stream(0, Transport.RTU, server_pty, server_pty)
    pipe = Pipeline(None)
    records = []
    for ts, data in packets:
        records += pipe.feed(Chunk(ts, stream, Direction.BUS, data))
    records += pipe.finish()
    assert not [r for r in records if r.kind is RecordKind.NOISE]
    frames = [r.frame for r in records if r.frame is not None]
    assert frames and all(f.crc_ok for f in frames)
    assert {f.unit for f in frames} == {0, 3, 4}


def test_mbmon_sim_serial_serves_rtu_until_ctrl_c(pty_pair: tuple[str, str]) -> None:
    """``mbmon sim --serial PTY`` as a user runs it: the address line, a command by a
    pymodbus RTU client on the other end, its console line, a clean stop."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    server_pty, client_pty = pty_pair
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "sim", "--serial", server_pty, "--baud", str(BAUD),
         "--unit", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert first == (
            f"mbmon sim: HRSS robot, unit 2, Modbus RTU on {server_pty} ({BAUD} baud, 8N1)\n"
        )
        assert "not a robot simulator" in proc.stdout.readline()
        client = ModbusSerialClient(
            client_pty, framer=FramerType.RTU, baudrate=BAUD, timeout=1, retries=0
        )
        assert client.connect()
        try:
            # pymodbus's serial server may say it is ready a moment before it reads its
            # port: ask until the line answers (a lost first request is not what is tested)
            deadline = time.monotonic() + 10
            while True:
                try:
                    rr = client.read_input_registers(100, count=1, device_id=2)
                    if not rr.isError():
                        break
                except Exception:  # pymodbus raises ModbusIOException on no answer
                    pass
                assert time.monotonic() < deadline, "mbmon sim never answered on the pty"
            assert rr.registers == [100]
            assert not client.write_registers(201, [103, 4], device_id=2).isError()
            assert not client.write_registers(200, [1], device_id=2).isError()  # Current TOOL[4]
            assert client.read_input_registers(200, count=2, device_id=2).registers == [1, 103]
        finally:
            client.close()
        line = proc.stdout.readline()
        assert "execute" in line and "success: Set Current TOOL[4]" in line
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert out.endswith("mbmon sim: stopped\n") and "Traceback" not in err
