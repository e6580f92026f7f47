"""SimRobot as a pure state machine: registers, the R200 handshake, motion over time.

Time is an input: every call passes ``now``, so motion and timers are checked
at exact instants. Words are unsigned on the wire; 32-bit values low word first.
"""

from __future__ import annotations

import pytest

from mbmon.sim.robot import EXC_ILLEGAL_ADDRESS, EXC_ILLEGAL_VALUE, MotionState, SimEvent, SimRobot
from mbmon.sim.spec import address_map, hrss_profile, join_i32, split_i32, u16

H, IR, C, D = "holding_registers", "input_registers", "coils", "discrete_inputs"


def w32(value: float) -> list[int]:
    low, high = split_i32(round(value * 1000))
    return [u16(low), u16(high)]


def r32(words: list[int] | int, at: int = 0) -> float:
    assert isinstance(words, list)
    return join_i32(words[at], words[at + 1]) / 1000


def run(robot: SimRobot, params: list[int], now: float) -> int:
    """R200 = 0, R201.. = params, R200 = 1; returns IR200."""
    assert robot.write(H, 200, [0], now) is None
    assert robot.write(H, 201, params, now) is None
    assert robot.write(H, 200, [1], now) is None
    got = robot.read(IR, 200, 1, now)
    assert isinstance(got, list)
    return got[0]


def ptp_joint(
    a1: float, speed: int = 50, acc: int = 100, tool: int = 1, base: int = 2
) -> list[int]:
    data = [0, 0, *w32(a1)] + [0] * 10 + [speed, acc, tool, base] + [0] * 8
    assert len(data) == 26
    return data


def cart(values: tuple[float, ...]) -> list[int]:
    out: list[int] = []
    for v in values:
        out += w32(v)
    return out


# --------------------------------------------------------------------------- the map


def test_the_address_map_is_the_profiles() -> None:
    robot = SimRobot()
    profile = hrss_profile()
    for table, spans in address_map().items():
        assert spans, table
        for start, end in spans:
            assert robot.check(table, start, end - start) is None
            assert profile.lookup(table, start) is not None
            assert profile.lookup(table, end - 1) is not None
            assert robot.check(table, end - 1, 2) == EXC_ILLEGAL_ADDRESS
            assert profile.lookup(table, end) is None or robot.check(table, end, 1) is None


@pytest.mark.parametrize(
    ("table", "address", "count"),
    [
        (C, 256, 1),  # between SI256 and DO[1]
        (C, 555, 2),  # past DO[256]
        (D, 250, 10),  # SO into the gap
        (IR, 32, 1),  # past SRW[32]
        (IR, 103, 1),
        (IR, 311, 2),  # A6 high word and the gap after it
        (IR, 300, 112),  # joints and pose in one read cross the gap 312..399
        (IR, 525, 1),
        (H, 101, 1),
        (H, 252, 1),
        (H, 1950, 1),  # past PR[50]
    ],
)
def test_reads_outside_the_map_are_exception_02(table: str, address: int, count: int) -> None:
    assert SimRobot().read(table, address, count, 0.0) == EXC_ILLEGAL_ADDRESS


def test_discrete_inputs_and_input_registers_are_read_only() -> None:
    robot = SimRobot()
    assert robot.write(D, 300, [1], 0.0) == EXC_ILLEGAL_ADDRESS
    assert robot.write(IR, 100, [5], 0.0) == EXC_ILLEGAL_ADDRESS


def test_r100_and_r200_refuse_values_outside_their_range_and_keep_the_old_one() -> None:
    events: list[SimEvent] = []
    robot = SimRobot(on_event=events.append)
    assert robot.write(H, 100, [0], 0.0) == EXC_ILLEGAL_VALUE
    assert robot.write(H, 100, [101], 0.0) == EXC_ILLEGAL_VALUE
    assert robot.write(H, 99 + 1, [u16(-5)], 0.0) == EXC_ILLEGAL_VALUE
    assert robot.write(H, 200, [2], 0.0) == EXC_ILLEGAL_VALUE
    assert robot.read(H, 100, 1, 0.0) == [100]
    assert robot.read(IR, 100, 1, 0.0) == [100]
    assert robot.write(H, 100, [35], 0.0) is None
    assert robot.read(IR, 100, 1, 0.0) == [35]
    assert [e.kind for e in events] == ["write-rejected"] * 4


def test_initial_state_so4_ready_di_pattern_excited_idle() -> None:
    robot = SimRobot()
    assert robot.read(D, 0, 8, 0.0) == [0, 0, 0, 1, 0, 0, 0, 0]  # SO4 Ready
    assert robot.read(D, 300, 8, 0.0) == [1, 0, 1, 0, 0, 0, 0, 0]  # DI[1], DI[3]
    assert robot.read(IR, 522, 3, 0.0) == [1, 200, MotionState.IDLE]
    assert robot.read(IR, 200, 2, 0.0) == [0, 0]  # status Ready before any command
    joints = robot.read(IR, 300, 12, 0.0)
    assert [r32(joints, i) for i in range(0, 12, 2)] == [0, 0, 0, 0, -90, 0]


def test_coils_and_user_signals() -> None:
    robot = SimRobot()
    assert robot.write(C, 300, [1, 1, 0, 0, 1], 0.0) is None
    assert robot.read(C, 300, 5, 0.0) == [1, 1, 0, 0, 1]
    robot.set_di(8, True)
    robot.set_so(9, True)
    robot.set_srw(1, -2)
    assert robot.read(D, 307, 1, 0.0) == [1]
    assert robot.read(D, 8, 1, 0.0) == [1]
    assert robot.read(IR, 0, 1, 0.0) == [0xFFFE]
    with pytest.raises(ValueError):
        robot.set_so(2, True)  # SO1..SO4 follow the state


# --------------------------------------------------------------------------- handshake and motion


def test_ptp_moves_a1_to_90_at_the_commanded_speed() -> None:
    robot = SimRobot(joint_speed=180.0)
    assert robot.write(H, 100, [90], 0.0) is None
    assert run(robot, ptp_joint(90), 1.0) == 1
    # 90 degrees of A1 (and 90 of A5, from -90 to 0) at 180 * 50 % * 90 % = 81 deg/s
    duration = 90 / 81
    assert robot.read(IR, 524, 1, 1.0) == [MotionState.RUNNING]
    assert robot.read(IR, 201, 1, 1.0) == [0]  # IR201 current action: PTP
    half = robot.read(IR, 300, 2, 1.0 + duration / 2)
    assert r32(half) == pytest.approx(45, abs=0.002)
    assert robot.read(D, 0, 4, 1.0 + duration / 2) == [1, 0, 0, 1]  # SO1 Run, SO4 Ready
    tcp = robot.read(IR, 520, 2, 1.0 + duration / 2)
    assert r32(tcp) > 0
    assert robot.read(IR, 524, 1, 1.0 + duration - 0.01) == [MotionState.RUNNING]
    assert robot.read(IR, 524, 1, 1.0 + duration + 0.01) == [MotionState.IDLE]
    joints = robot.read(IR, 300, 12, 1.0 + duration + 0.01)
    assert joints == [24464, 1] + [0] * 10  # Table 46's words: A1 = 90.000
    assert robot.read(D, 0, 4, 5.0) == [0, 0, 0, 1]
    assert robot.read(IR, 520, 2, 5.0) == [0, 0]


def test_r200_must_return_to_0_before_the_next_command_executes() -> None:
    events: list[SimEvent] = []
    robot = SimRobot(on_event=events.append)
    assert run(robot, [104, 7], 0.0) == 1  # Set Current BASE[7]
    assert robot.write(H, 201, [103, 3], 0.1) is None  # Set Current TOOL[3] ...
    assert robot.write(H, 200, [1], 0.1) is None  # ... but R200 is still 1
    assert robot.current_tool == 0 and robot.executed == 1
    assert events[-1].kind == "ignored"
    assert robot.write(H, 200, [0], 0.2) is None
    assert robot.write(H, 200, [1], 0.2) is None
    assert robot.current_tool == 3 and robot.executed == 2


def test_one_request_writing_parameters_and_r200_executes_after_storing_them() -> None:
    robot = SimRobot()
    assert robot.write(H, 200, [1, 104, 9], 0.0) is None  # R200 = 1, R201 = 104, R202 = 9
    assert robot.current_base == 9 and robot.status == 1


def test_motion_commands_queue_while_moving_ir102_counts_them_ir101_shows_the_code() -> None:
    robot = SimRobot(joint_speed=100.0)
    params = ptp_joint(10, speed=100)
    params[25] = 77  # R226 custom command code
    assert run(robot, params, 0.0) == 1
    assert run(robot, ptp_joint(20, speed=100), 0.0) == 1
    assert run(robot, ptp_joint(30, speed=100), 0.0) == 1
    assert robot.read(IR, 101, 2, 0.01) == [77, 2]
    # the first: 90 deg of A5 take 0.9 s; then 10 deg each take 0.1 s
    assert robot.read(IR, 101, 2, 0.95) == [0, 1]
    assert robot.read(IR, 524, 1, 1.09) == [MotionState.RUNNING]
    assert robot.read(IR, 524, 1, 1.11) == [MotionState.IDLE]
    assert r32(robot.read(IR, 300, 2, 1.2)) == pytest.approx(30)


def test_motion_stop_ends_the_motion_and_clears_the_queue() -> None:
    robot = SimRobot()
    run(robot, ptp_joint(90), 0.0)
    run(robot, ptp_joint(0), 0.0)
    assert run(robot, [6], 0.2) == 1
    assert robot.read(IR, 102, 1, 0.2) == [0]
    assert robot.read(IR, 524, 1, 0.2) == [MotionState.IDLE]
    a1 = r32(robot.read(IR, 300, 2, 0.2))
    assert 0 < a1 < 90
    assert r32(robot.read(IR, 300, 2, 5.0)) == a1


def test_lin_moves_xyz_at_the_tcp_speed_and_reports_it_in_ir520() -> None:
    robot = SimRobot()
    start = (400.0, 0.0, 500.0)
    params = [1, 1, *cart((400, 300, 100, 180, 0, 0)), 500, 100, 0, 0, 0] + [0] * 7
    assert run(robot, params, 0.0) == 1
    length = ((0**2) + 300**2 + 400**2) ** 0.5  # 500 mm at 500 mm/s: 1 s
    assert length == 500
    assert r32(robot.read(IR, 520, 2, 0.5)) == pytest.approx(500)
    pose = robot.read(IR, 400, 12, 0.5)
    assert [r32(pose, i) for i in (0, 2, 4)] == pytest.approx([400, 150, 300], abs=0.01)
    assert robot.read(IR, 524, 1, 1.01) == [MotionState.IDLE]
    pose = robot.read(IR, 400, 12, 1.01)
    assert [r32(pose, i) for i in range(0, 12, 2)] == [400, 300, 100, 180, 0, 0]
    assert tuple(robot.joints) == (0, 0, 0, 0, -90, 0)  # no kinematics: joints stay
    assert start == (400.0, 0.0, 500.0)


def test_circ_passes_through_the_auxiliary_point_on_a_circle() -> None:
    robot = SimRobot()
    # from (400, 0, 500) through (500, 100, 500) to (600, 0, 500): a half circle of radius 100
    aux = cart((500, 100, 500, 180, 0, 0))
    end = cart((600, 0, 500, 180, 0, 0))
    params = [2, *aux, *end, 100, 100, 0, 0, 0] + [0] * 7
    assert len(params) == 37
    assert run(robot, params, 0.0) == 1
    duration = 3.14159265 * 100 / 100
    mid = robot.read(IR, 400, 6, duration / 2)
    assert [r32(mid, i) for i in (0, 2, 4)] == pytest.approx([500, 100, 500], abs=0.01)
    quarter = robot.read(IR, 400, 6, duration / 4)
    x, y = r32(quarter, 0) - 500, r32(quarter, 2)
    assert (x * x + y * y) ** 0.5 == pytest.approx(100, abs=0.01)
    assert robot.read(IR, 524, 1, duration + 0.01) == [MotionState.IDLE]
    assert r32(robot.read(IR, 400, 2, duration + 0.01)) == 600


def test_ptp_cartesian_moves_the_pose_and_external_axes_at_speed_percent() -> None:
    robot = SimRobot(cart_speed=1000.0)
    # PTP {X 400, Y 300, Z 100, A 180, B 0, C 0, E1 50} Vel=10% Code=12 (Table 17, point type 1)
    params = [0, 1, *cart((400, 300, 100, 180, 0, 0)), 10, 100, 0, 0, 1, *w32(50), 0, 0, 0, 0, 12]
    assert len(params) == 26
    assert run(robot, params, 0.0) == 1
    # 500 mm at 1000 mm/s x 10 % = 100 mm/s: 5 s; E1 arrives with the pose
    assert robot.read(IR, 101, 1, 2.5) == [12]  # IR101: the custom code of the running motion
    assert r32(robot.read(IR, 520, 2, 2.5)) == pytest.approx(100)  # IR520 TCP speed
    pose = robot.read(IR, 400, 12, 2.5)
    assert [r32(pose, i) for i in (0, 2, 4)] == pytest.approx([400, 150, 300], abs=0.01)
    assert robot.state()["ext"][0] == pytest.approx(25)
    assert robot.read(IR, 524, 1, 4.99) == [MotionState.RUNNING]
    assert robot.read(IR, 524, 1, 5.01) == [MotionState.IDLE]
    assert robot.read(IR, 101, 1, 5.01) == [0] and robot.read(IR, 520, 2, 5.01) == [0, 0]
    pose = robot.read(IR, 400, 12, 5.01)
    assert [r32(pose, i) for i in range(0, 12, 2)] == [400, 300, 100, 180, 0, 0]
    assert robot.state()["ext"] == (50, 0, 0)
    assert tuple(robot.joints) == (0, 0, 0, 0, -90, 0)  # no kinematics: joints stay


def test_circ_reports_its_code_in_ir101_and_its_speed_in_ir520() -> None:
    robot = SimRobot()
    aux = cart((500, 100, 500, 180, 0, 0))
    end = cart((600, 0, 500, 180, 0, 0))
    params = [2, *aux, *end, 50, 100, 0, 0, 0] + [0] * 6 + [u16(-7)]  # R237 code -7
    assert len(params) == 37
    assert run(robot, params, 0.0) == 1
    assert robot.read(IR, 101, 1, 1.0) == [u16(-7)]
    assert r32(robot.read(IR, 520, 2, 1.0)) == pytest.approx(50)
    assert robot.read(IR, 524, 1, 1.0) == [MotionState.RUNNING]


def test_jog_runs_while_r200_stays_1_and_stops_when_it_returns_to_0() -> None:
    robot = SimRobot()
    assert run(robot, [3, 0, 1], 0.0) == 1  # JOG A1 + (Example 5, Table 48)
    assert robot.read(IR, 524, 1, 0.0) == [MotionState.RUNNING]
    assert r32(robot.read(IR, 300, 2, 2.0)) == pytest.approx(20)  # 10 deg/s at 100 %
    assert robot.write(H, 200, [0], 2.0) is None
    assert robot.read(IR, 524, 1, 2.0) == [MotionState.IDLE]
    assert r32(robot.read(IR, 300, 2, 9.0)) == pytest.approx(20)
    assert run(robot, [3, 8, u16(-1)], 10.0) == 1  # JOG Z -
    assert r32(robot.read(IR, 404, 2, 11.0)) == pytest.approx(450)  # 50 mm/s


def test_jog_and_go_home_fail_while_a_motion_runs() -> None:
    robot = SimRobot()
    run(robot, ptp_joint(90), 0.0)
    assert run(robot, [3, 0, 1], 0.1) == 2
    assert run(robot, [4, 1], 0.1) == 2


def test_go_home_runs_to_home_while_r200_stays_1() -> None:
    robot = SimRobot(joint_speed=100.0)
    home = cart((10, 20, 30, 0, 0, 0))  # A1..A6 as 6 x i32
    assert run(robot, [105, *home], 0.0) == 1  # Set HOME
    assert run(robot, [4, 1], 0.0) == 1  # GO HOME at 20 %: 20 deg/s, 90 deg of A5 -> 4.5 s
    assert robot.read(IR, 524, 1, 4.0) == [MotionState.RUNNING]
    assert robot.read(IR, 524, 1, 4.6) == [MotionState.IDLE]
    assert tuple(robot.joints) == (10, 20, 30, 0, 0, 0)
    assert run(robot, ptp_joint(90, speed=100), 5.0) == 1
    robot.step(7.0)
    assert run(robot, [4, 1], 7.0) == 1
    assert robot.write(H, 200, [0], 7.5) is None  # released half way: it stops
    a1 = robot.joints[0]
    assert 10 < a1 < 90
    assert robot.read(IR, 524, 1, 20.0) == [MotionState.IDLE] and robot.joints[0] == a1


def test_si2_hold_pauses_the_motion_and_so2_shows_it() -> None:
    robot = SimRobot(joint_speed=100.0)
    run(robot, ptp_joint(10, speed=100), 0.0)  # 0.9 s (A5 moves 90 deg)
    assert robot.write(C, 1, [1], 0.45) is None  # SI2 Hold
    assert robot.read(IR, 524, 1, 5.0) == [MotionState.HOLD]
    assert robot.read(D, 0, 4, 5.0) == [0, 1, 0, 1]
    assert robot.read(IR, 520, 2, 5.0) == [0, 0]
    assert robot.joints[4] == pytest.approx(-45)
    assert robot.write(C, 1, [0], 5.0) is None
    assert robot.read(IR, 524, 1, 5.44) == [MotionState.RUNNING]
    assert robot.read(IR, 524, 1, 5.46) == [MotionState.IDLE]


def test_si3_stop_ends_the_motion() -> None:
    robot = SimRobot()
    run(robot, ptp_joint(90), 0.0)
    assert robot.write(C, 2, [1], 0.2) is None
    assert robot.read(IR, 524, 1, 0.2) == [MotionState.IDLE]


def test_a_fault_stops_motion_sets_so3_and_ir502_and_motion_commands_fail() -> None:
    robot = SimRobot()
    run(robot, ptp_joint(90), 0.0)
    robot.set_fault(0x0A200001, now=0.1)
    assert robot.read(IR, 524, 1, 0.2) == [MotionState.IDLE]
    assert robot.read(D, 0, 4, 0.2) == [0, 0, 1, 0]
    assert robot.read(IR, 502, 2, 0.2) == [0x0001, 0x0A20]  # low word = error code 2
    assert run(robot, ptp_joint(0), 0.3) == 2
    assert run(robot, [103, 2], 0.3) == 1  # a non-motion command still works
    robot.clear_fault()
    assert robot.read(D, 0, 4, 0.4) == [0, 0, 0, 1]
    assert run(robot, ptp_joint(0), 0.4) == 1


# --------------------------------------------------------------------------- data commands


def test_set_pr_lands_in_the_pr_holding_registers_and_get_pr_returns_it() -> None:
    robot = SimRobot()
    # Example 7 (Table 50): $PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0}
    assert run(robot, [100, 2, 2, *cart((90, 0, 0, 0, 0, 0))], 0.0) == 1
    block = robot.read(H, 1019, 19, 0.0)
    assert block[:3] == [2, 24464, 1] and block[3:] == [0] * 16
    # Example 8 (Table 52): Get PR[2] -> IR202 = 2, IR203 = 2, IR204..205 = 24464, 1
    assert run(robot, [200, 2], 0.0) == 1
    assert robot.read(IR, 200, 16, 0.0) == [1, 200, 2, 2, 24464, 1] + [0] * 10
    # a client can write PR[3] directly (Table 15) and move to it
    assert robot.write(H, 1038, [1, *w32(45)], 0.0) is None
    assert robot.pr(3) == (1, (45000,) + (0,) * 8)
    assert run(robot, [0, 2, 3] + [0] * 11 + [100, 100, 0, 0, 0] + [0] * 7, 0.0) == 1
    robot.step(10.0)
    assert robot.joints[0] == 45


def test_prs_beyond_50_are_kept_outside_the_registers() -> None:
    robot = SimRobot()
    assert run(robot, [100, 4000, 1, *cart((1, 2, 3, 4, 5, 6))], 0.0) == 1
    assert run(robot, [200, 4000], 0.0) == 1
    got = robot.read(IR, 202, 14, 0.0)
    assert got[:2] == [4000, 1] and [r32(got, i) for i in range(2, 14, 2)] == [1, 2, 3, 4, 5, 6]


def test_moving_to_a_null_position_register_fails() -> None:
    robot = SimRobot()
    assert run(robot, [1, 2, 5] + [0] * 11 + [100, 100, 0, 0, 0] + [0] * 7, 0.0) == 2


def test_tool_base_current_and_home_round_trip_through_get() -> None:
    robot = SimRobot()
    assert run(robot, [101, 4, *cart((1, 2, 3, 4, 5, 6))], 0.0) == 1
    assert run(robot, [201, 4], 0.0) == 1
    got = robot.read(IR, 202, 13, 0.0)
    assert got[0] == 4 and [r32(got, i) for i in range(1, 13, 2)] == [1, 2, 3, 4, 5, 6]
    assert run(robot, [102, 31, *cart((-1, 0, 0, 0, 0, 45))], 0.0) == 1
    assert run(robot, [202, 31], 0.0) == 1
    got = robot.read(IR, 202, 13, 0.0)
    assert got[0] == 31 and r32(got, 1) == -1 and r32(got, 11) == 45
    assert run(robot, [103, 15], 0.0) == 1 and run(robot, [203], 0.0) == 1
    assert robot.read(IR, 201, 3, 0.0) == [203, 15, 0]  # returns cleared past the layout
    assert run(robot, [104, 0], 0.0) == 1 and run(robot, [204], 0.0) == 1
    assert robot.read(IR, 202, 1, 0.0) == [0]
    assert run(robot, [105, *cart((0, -90, 90, 0, 0, 0))], 0.0) == 1
    assert run(robot, [205], 0.0) == 1
    got = robot.read(IR, 202, 12, 0.0)
    assert [r32(got, i) for i in range(0, 12, 2)] == [0, -90, 90, 0, 0, 0]


def test_t_stop_starts_and_stops_a_timer_in_0_001_s() -> None:
    robot = SimRobot()
    assert run(robot, [5, 3, 0], 1.0) == 1  # T_STOP Timer[3] FALSE: start timing
    assert r32(robot.read(H, 304, 2, 3.5)) == pytest.approx(2.5)  # Timer[3] at 298+2*3
    assert robot.write(H, 304, [0, 0], 4.0) is None  # reset while running
    assert r32(robot.read(H, 304, 2, 4.25)) == pytest.approx(0.25)
    assert run(robot, [5, 3, 1], 5.0) == 1  # stop timing
    assert r32(robot.read(H, 304, 2, 9.0)) == pytest.approx(1.0)


def test_counters_are_plain_32_bit_registers() -> None:
    robot = SimRobot()
    assert robot.write(H, 438, w32(-0.5), 0.0) is None  # Counter[20] = -500 (0.001 units)
    assert join_i32(*robot.read(H, 438, 2, 0.0)) == -500  # type: ignore[misc]
