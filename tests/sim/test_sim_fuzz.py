"""Any sequence of client writes and reads, at any times, keeps SimRobot consistent.

No exception escapes; every answer is the requested number of values or an
exception code (02 address, 03 value); IR200, IR524, SO1..SO4 stay in their
ranges; time never runs backwards for the motion.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.sim.robot import SimEvent, SimRobot

TABLES = ("coils", "discrete_inputs", "input_registers", "holding_registers")
COMMANDS = (0, 1, 2, 3, 4, 5, 6, 100, 101, 102, 103, 104, 105, 200, 201, 202, 203, 204, 205, 7)

word = st.integers(0, 0xFFFF)
small = st.sampled_from([0, 1, 2, 3, 15, 16, 31, 32, 50, 51, 100, 200, 4000, 4001, 0xFFFF])
#: a write into the command block: R200..R251 with a known command number, small values
command_write = st.builds(
    lambda code, values, execute: ("holding_registers", 200, [execute, code, *values]),
    st.sampled_from(COMMANDS),
    st.lists(st.one_of(small, word), max_size=50),
    st.sampled_from([0, 1]),
)
any_write = st.builds(
    lambda table, address, values: (table, address, values),
    st.sampled_from(("coils", "holding_registers")),
    st.integers(0, 2000),
    st.lists(word, min_size=1, max_size=20),
)
read = st.builds(
    lambda table, address, count: (table, address, count),
    st.sampled_from(TABLES),
    st.integers(0, 2000),
    st.integers(1, 125),
)
op = st.tuples(
    st.sampled_from(["write", "write", "read"]),
    st.one_of(command_write, any_write, read),
    st.floats(0, 3, allow_nan=False),
)


@settings(max_examples=300, deadline=None)
@given(st.lists(op, max_size=40))
def test_any_client_traffic_keeps_the_robot_consistent(ops: list) -> None:  # type: ignore[type-arg]
    events: list[SimEvent] = []
    robot = SimRobot(on_event=events.append)
    now = 0.0
    for kind, args, dt in ops:
        now += dt
        if kind == "write" and isinstance(args[2], list):
            table, address, values = args
            got = robot.write(table, address, values, now)
            assert got in (None, 2, 3)
        else:
            table, address, count = args if not isinstance(args[2], list) else (*args[:2], 1)
            got = robot.read(table, address, count, now)
            if isinstance(got, int):
                assert got == 2
            else:
                assert len(got) == count
                assert all(0 <= v <= 0xFFFF for v in got)
        status, action = robot.read("input_registers", 200, 2, now)  # type: ignore[misc]
        assert status in (0, 1, 2)
        assert action in COMMANDS[:-1]  # IR201: only ever a Table 16 number (0 at start)
        assert robot.read("input_registers", 524, 1, now)[0] in (1, 2, 3)  # type: ignore[index]
        so = robot.read("discrete_inputs", 0, 4, now)
        assert so[3] == 1 and so[2] == 0  # no fault raised by traffic: Ready, no Fault
        assert not (so[0] and so[1])  # never Run and Held at once
    assert robot.event_error is None
    assert all(e.kind in ("execute", "motion", "stop", "ignored", "write-rejected") for e in events)


def test_a_callback_that_raises_is_detached_and_the_robot_goes_on() -> None:
    def broken(_: SimEvent) -> None:
        raise BrokenPipeError("stdout closed")

    robot = SimRobot(on_event=broken)
    assert robot.write("holding_registers", 200, [1, 104, 3], 0.0) is None
    assert robot.current_base == 3 and robot.status == 1
    assert isinstance(robot.event_error, BrokenPipeError) and robot.on_event is None
