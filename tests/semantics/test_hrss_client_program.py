"""Manual §5.4.5.2: robot A drives robot B (the HRSS server) over Modbus TCP, replayed.

Each MBC_* line of the program becomes one request and its answer, in the
program's order. Assumptions, also in docs/commands.md: the program's start
address is the address on the wire (the §5.5.2.7 monitor example shows
MBC_WRITE_HOLDING to 201 as ``10 00 C9 ...``), and MBC_WRITE_HOLDING sends
function 0x10 even for one word. The answers are what a robot B would say:
speed 100 %, DI[1]..DI[8] = 1,0,1,0,0,0,0,0, motion Running while the PTP
runs, then Idle.
"""

from __future__ import annotations

from test_hrss_commands import STREAM, Script, notes, phases, updates, warnings

from mbmon.model import Annotation, Phase
from mbmon.semantics.hrss import HrssSession

PTP = "PTP {A1 90, A2 0, A3 0, A4 0, A5 0, A6 0} Vel=50% Acc=100% TOOL[1] BASE[2]"

#: (program line, request PDU, response PDU): the part of the program before the motion.
SETUP = [
    (4, "04 0064 0001", "04 02 0064"),  # MBC_READ_INPUT(1,100,READ_DATA,'W',1): B's speed %
    (7, "10 0064 0001 02 005A", "10 0064 0001"),  # MBC_WRITE_HOLDING(1,100,...,'W',1): 90 %
    (8, "02 012C 0008", "02 01 05"),  # MBC_READ_DINPUT(1,300,READ_DATA,8): DI[1]..DI[8]
    (21, "0F 012C 0005 01 13", "0F 012C 0005"),  # MBC_WRITE_COIL(1,300,WRITE_DATA,5): DO[1..5]
    (26, "10 00C8 0001 02 0000", "10 00C8 0001"),  # MBC_WRITE_HOLDING(1,200,...,'W',1): R200 = 0
]
#: Lines 28-36: WRITE_DATA[1..26] = 0, 0, 24464, 1, 0 x10, 50, 100, 1, 2, 0 x8 -> R201..R226.
PARAMS = (
    36,
    "10 00C9 001A 34"
    " 0000 0000 5F90 0001 0000 0000 0000 0000 0000 0000 0000 0000 0000 0000"
    " 0032 0064 0001 0002 0000 0000 0000 0000 0000 0000 0000 0000",
    "10 00C9 001A",
)
EXECUTE = (38, "10 00C8 0001 02 0001", "10 00C8 0001")  # MBC_WRITE_HOLDING(1,200,...): R200 = 1
READ_524 = "04 020C 0001"  # MBC_READ_INPUT(1,524,READ_DATA,'W',1)
RUNNING, IDLE = "04 02 0002", "04 02 0001"


def play(s: Script, rows: list[tuple[int, str, str]], dt: float | None = None) -> list[Annotation]:
    out: list[Annotation] = []
    for _line, q, r in rows:
        a1, a2 = s((bytes.fromhex(q), bytes.fromhex(r)), dt=dt)
        out += [a1] if a2 is None else [a1, a2]
    return out


def program(polls_running: int) -> list[tuple[int, str, str]]:
    """Lines 39-42: read IR524, then WHILE it is 2 read it again every 0.1 s."""
    return [(39 if i == 0 else 41, READ_524, RUNNING) for i in range(polls_running)] + [
        (41, READ_524, IDLE)
    ]


def test_the_ptp_is_reconstructed_and_the_polling_shows_the_motion() -> None:
    s = Script()
    setup = play(s, SETUP)
    assert updates(setup) == [] and notes(setup) == []
    assert setup[1].state == {"speed_pct": 100.0}  # line 4's answer
    written = play(s, [PARAMS])
    assert [(c.phase, c.text, c.code) for c in updates(written)] == [(Phase.WRITTEN, PTP, 0)]
    execute = play(s, [EXECUTE])
    assert [(c.phase, c.text, c.code) for c in updates(execute)] == [(Phase.EXECUTING, PTP, 0)]
    assert notes(execute) == [f"execute: {PTP}"]
    polls = play(s, program(polls_running=5), dt=0.1)
    answers = polls[1::2]
    running = {"speed_pct": 100.0, "motion_state": 2.0}
    idle = {"speed_pct": 100.0, "motion_state": 1.0}
    assert [a.state for a in answers] == [running, None, None, None, None, idle]
    # the last answer: 6 reads 0.1 s apart after the execute's answer, 4 ms latency each
    assert [a.notes for a in answers] == [("motion: Running (2)",)] + [()] * 4 + [
        ("motion: Running (2) -> Idle (1)", f"motion done: {PTP} (0.628 s after R200 = 1)")
    ]
    assert all(a.commands == () for a in polls)
    assert warnings(setup + written + execute + polls) == []


def test_a_long_motion_is_not_a_command_that_never_completes() -> None:
    s = Script(HrssSession(STREAM, 1, complete_timeout=10.0))
    play(s, [*SETUP, PARAMS, EXECUTE])
    polls = play(s, program(polls_running=150), dt=0.1)  # 15 s of Running
    assert warnings(polls) == []
    assert notes(polls[-1:])[-1].startswith(f"motion done: {PTP} (15.")


def test_running_the_program_twice_resets_r200_first_so_no_warning() -> None:
    s = Script()
    play(s, [*SETUP, PARAMS, EXECUTE, *program(2)])
    again = play(s, [*SETUP, PARAMS, EXECUTE, *program(2)])
    assert phases(again) == [Phase.WRITTEN, Phase.EXECUTING]


def test_without_line_26_the_second_run_executes_without_reset() -> None:
    s = Script()
    play(s, [*SETUP, PARAMS, EXECUTE, *program(2)])
    again = play(s, [*SETUP[:-1], PARAMS, EXECUTE, *program(2)])
    assert phases(again) == [Phase.WRITTEN, Phase.WARNING, Phase.EXECUTING]
    assert warnings(again)[0].params["warning"] == "no_reset"


def test_robot_b_never_moving_is_reported_once() -> None:
    s = Script(HrssSession(STREAM, 1, complete_timeout=10.0))
    play(s, [*SETUP, PARAMS, EXECUTE])
    idle = play(s, [(41, READ_524, IDLE)] * 120, dt=0.1)  # 12 s of Idle after the execute
    [warn] = warnings(idle)
    assert warn.text == f"never completed: {PTP} (robot never moved 10 s after R200 = 1)"
    assert warn.code == 0
