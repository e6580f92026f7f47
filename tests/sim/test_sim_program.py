"""The manual's §5.4.5.2 program (plus LIN, Set/Get PR, JOG) against SimServer over TCP.

A pymodbus client runs :func:`mbmon.sim.program.run_program` against a server
on 127.0.0.1; the robot must end at A1 = 90°. The bytes the server saw and
sent are then decoded by mbmon's own pipeline with the HRSS profile, which must
reconstruct the commands the program sent and their outcomes.
"""

from __future__ import annotations

import threading
import time

import pytest
from pymodbus.client import ModbusTcpClient

from mbmon.model import Chunk, Direction, Phase, RecordKind, Stream, Transport
from mbmon.pipeline import Pipeline
from mbmon.semantics.annotate import annotator_for
from mbmon.sim.program import ProgramError, Step, run_program
from mbmon.sim.server import SimServer

PTP = "PTP {A1 90, A2 0, A3 0, A4 0, A5 0, A6 0} Vel=50% Acc=100% TOOL[1] BASE[2]"
LIN = "LIN {X -300, Y 300, Z 400, A 180, B 0, C 90} Vel=1000mm/s Acc=100% TOOL[3] BASE[7]"


def test_the_5452_program_reaches_a1_90_and_the_analyzer_reconstructs_it() -> None:
    packets: list[tuple[float, bool, bytes]] = []
    lock = threading.Lock()

    def tap(sending: bool, data: bytes) -> None:
        with lock:
            packets.append((time.time(), sending, data))

    steps: list[Step] = []
    told: list[tuple[str, int]] = []  # (part, steps answered when on_part came)
    with SimServer(on_packet=tap) as server:
        result = run_program(
            server.host,
            server.port,
            on_step=steps.append,
            on_part=lambda part: told.append((part, len(steps))),
            jog_seconds=0.4,
        )
        state = server.snapshot()

    # the program's own view ($C[1..9] and what it read back)
    assert result.speed_before == 100
    assert result.di == (1, 0, 1, 0, 0, 0, 0, 0)
    assert result.joints == (90, 0, 0, 0, 0, 0)
    assert result.pose == (-300, 300, 400, 180, 0, 90)  # read back after the LIN
    assert result.statuses == {"LIN": 1, "Set PR": 1, "Get PR": 1, "JOG": 1}
    assert result.pr2[:4] == (2, 2, 24464, 1)  # Table 52: PR[2], Cartesian, X = 90
    assert result.jog_moved > 1.0  # 10 deg/s x 90 % for 0.4 s
    assert result.jog_after_stop == 0
    # the robot's view: speed 90 %, DO[1..5] written, A1 at 90 + the JOG
    assert state["speed_pct"] == 90 and state["motion_state"] == 1
    # the JOG is measured from the pose before R200 = 1 to the pose once stopped:
    # all the robot moved, to the register's 0.001 degree
    assert result.jog_from == 90
    assert abs(state["joints"][0] - result.jog_to) <= 0.0005
    assert result.jog_moved == pytest.approx(state["joints"][0] - 90, abs=0.0005)
    assert state["pose"] == (-300, 300, 400, 180, 0, 90)
    assert server.robot.coils[300:305] == [1, 1, 0, 0, 1]
    # the steps: the §5.4.5.2 lines in order, numbered, each answered
    head = [(s.part, s.function, s.address) for s in steps[:7]]
    assert head == [
        ("5.4.5.2", 4, 100),
        ("5.4.5.2", 16, 100),
        ("5.4.5.2", 2, 300),
        ("5.4.5.2", 15, 300),
        ("5.4.5.2", 16, 200),
        ("5.4.5.2", 16, 201),
        ("5.4.5.2", 16, 200),
    ]
    assert steps[5].values[:4] == (0, 0, 24464, 1) and len(steps[5].values) == 26
    polls = [s for s in steps if s.part == "5.4.5.2" and s.address == 524]
    assert polls[0].result == (2,) and polls[-1].result == (1,)  # Running ... Idle
    assert [s.index for s in steps] == list(range(1, len(steps) + 1))
    assert {s.part for s in steps} == {"5.4.5.2", "LIN", "Set PR", "Get PR", "JOG"}
    # on_part comes before each extra part's first request
    first = {p: next(i for i, s in enumerate(steps) if s.part == p) for p, _ in told}
    assert told == [(p, first[p]) for p in ("LIN", "Set PR", "Get PR", "JOG")]

    # mbmon's decoder on the server's traffic (one TCP connection: the program's)
    stream = Stream(0, Transport.TCP, "127.0.0.1:50000", f"127.0.0.1:{server.port}")
    pipe = Pipeline(annotator_for([f"{server.host}:{server.port}=hrss"]))
    records = []
    for ts, sending, data in packets:
        direction = Direction.S2C if sending else Direction.C2S
        records += pipe.feed(Chunk(ts, stream, direction, data))
    records += pipe.finish()
    assert not [r for r in records if r.kind in (RecordKind.NOISE, RecordKind.EXCEPTION)]
    frames = [r for r in records if r.kind in (RecordKind.REQUEST, RecordKind.RESPONSE)]
    assert len(frames) == 2 * len(steps)
    commands = [(r.command.phase, r.command.text) for r in records if r.command is not None]
    assert (Phase.EXECUTING, PTP) in commands
    assert (Phase.SUCCESS, LIN) in commands
    assert (Phase.SUCCESS, "$PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0}") in commands
    assert (Phase.RETURNED, "PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0}") in commands
    assert (Phase.SUCCESS, "JOG A1 +") in commands
    assert not [c for c in commands if c[0] in (Phase.FAIL, Phase.WARNING)]
    notes = [n for r in records for n in r.notes]
    assert any(n.startswith(f"motion done: {PTP}") for n in notes)
    assert any(n.startswith("stop: JOG A1 +") for n in notes)


def test_the_program_reports_a_server_that_refuses() -> None:
    with SimServer() as server:
        server.call(lambda robot, now: robot.set_fault(0x1234, now))
        # a fault does not stop the §5.4.5.2 part (it never reads IR200) but the robot never
        # moves: A1 stays where it was
        result = run_program(server.host, server.port, extras=False)
        assert result.joints == (0, 0, 0, 0, -90, 0)
        assert server.robot.status == 2
    with pytest.raises(ProgramError):
        run_program(server.host, server.port)  # the server is gone


def test_the_program_runs_on_a_client_it_is_given() -> None:
    with SimServer(unit=7) as server:
        client = ModbusTcpClient(server.host, port=server.port, timeout=3, retries=0)
        assert client.connect()
        try:
            result = run_program(client=client, unit=7, extras=False)
            assert result.joints[0] == 90
            assert client.connected  # not closed: the caller owns it
        finally:
            client.close()
