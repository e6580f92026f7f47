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
