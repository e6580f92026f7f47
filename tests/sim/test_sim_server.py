"""SimServer on 127.0.0.1 with a real pymodbus client: Table 16 commands, exceptions, units.

Each command of Table 16 is sent the way the manual says (R200 = 0, R201..,
R200 = 1) with parameters inside and outside the ranges of Tables 17-43, and
IR200 must read 1 (success) or 2 (fail); IR201 names the command.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from pymodbus.client import ModbusTcpClient

from mbmon.sim.server import SimServer
from mbmon.sim.spec import decode_returns, split_i32, u16

UNIT = 1


def w32(value: float) -> list[int]:
    low, high = split_i32(round(value * 1000))
    return [u16(low), u16(high)]


def six(*values: float) -> list[int]:
    out: list[int] = []
    for v in values:
        out += w32(v)
    return out


def motion(point: int, target: list[int], speed: int, acc: int = 100, tool: int = 0,
           base: int = 0, ext: int = 0) -> list[int]:  # fmt: skip
    """R202..R226 of PTP/LIN (Tables 17-20)."""
    body = [point, *target]
    body += [0] * (13 - len(body))  # R202..R214
    return [*body, speed, acc, tool, base, ext, 0, 0, 0, 0, 0, 0, 0]


JOINT90 = six(90, 0, 0, 0, 0, 0)
CART = six(300, 100, 400, 180, 0, 90)


def circ(speed: int, tool: int = 0) -> list[int]:
    return [*six(400, 50, 500, 180, 0, 0), *six(420, 0, 500, 180, 0, 0), speed, 50, tool, 0, 0]


#: (case id, R201, R202.., expected IR200): Table 16 with Tables 17-43's ranges.
CASES: list[tuple[str, int, list[int], int]] = [
    ("PTP joint (Table 46)", 0, motion(0, JOINT90, 50, 100, 1, 2), 1),
    ("PTP Cartesian", 0, motion(1, CART, 10, 20, 3, 7), 1),
    ("PTP $PR[2]", 0, motion(2, [2], 50), 1),
    ("PTP speed 0", 0, motion(0, JOINT90, 0), 2),
    ("PTP speed 201", 0, motion(0, JOINT90, 201), 2),
    ("PTP speed 200", 0, motion(0, JOINT90, 200), 1),
    ("PTP acc 0", 0, motion(0, JOINT90, 50, 0), 2),
    ("PTP acc 101", 0, motion(0, JOINT90, 50, 101), 2),
    ("PTP TOOL 16", 0, motion(0, JOINT90, 50, 100, 16), 2),
    ("PTP BASE 32", 0, motion(0, JOINT90, 50, 100, 0, 32), 2),
    ("PTP external axis flag 2", 0, motion(0, JOINT90, 50, ext=2), 2),
    ("PTP point type 3", 0, motion(3, JOINT90, 50), 2),
    ("PTP $PR[4001]", 0, motion(2, [4001], 50), 2),
    ("PTP $PR[0]", 0, motion(2, [0], 50), 2),
    ("PTP $PR[9] NULL", 0, motion(2, [9], 50), 2),
    (
        "LIN Cartesian (Example 4)",
        1,
        motion(1, six(-300, 300, 400, 180, 0, 90), 1000, 100, 3, 7),
        1,
    ),
    ("LIN $PR[2] (Example 9)", 1, motion(2, [2], 1000, 100, 3, 7), 1),
    ("LIN speed 6000", 1, motion(1, CART, 6000), 1),
    ("LIN speed 6001", 1, motion(1, CART, 6001), 2),
    ("LIN speed 0", 1, motion(1, CART, 0), 2),
    ("CIRC", 2, circ(250), 1),
    ("CIRC speed 6001", 2, circ(6001), 2),
    ("CIRC TOOL 16", 2, circ(100, 16), 2),
    ("JOG A1 +", 3, [0, 1], 1),
    ("JOG E3 -", 3, [14, u16(-1)], 1),
    ("JOG stop", 3, [5, 0], 1),
    ("JOG axis 15", 3, [15, 1], 2),
    ("JOG direction 2", 3, [0, 2], 2),
    ("GO HOME", 4, [1], 1),
    ("GO HOME stop", 4, [0], 1),
    ("GO HOME enable 2", 4, [2], 2),
    ("T_STOP Timer[1] start", 5, [1, 0], 1),
    ("T_STOP Timer[20] stop", 5, [20, 1], 1),
    ("T_STOP Timer[21]", 5, [21, 1], 2),
    ("T_STOP Timer[0]", 5, [0, 1], 2),
    ("T_STOP state 2", 5, [1, 2], 2),
    ("Motion Stop", 6, [], 1),
    ("Set PR Cartesian (Example 7)", 100, [2, 2, *six(90, 0, 0, 0, 0, 0)], 1),
    ("Set PR joint", 100, [4000, 1, *six(1, 2, 3, 4, 5, 6)], 1),
    ("Set PR NULL", 100, [7, 0], 1),
    ("Set PR[0]", 100, [0, 2, *six(0, 0, 0, 0, 0, 0)], 2),
    ("Set PR[4001]", 100, [4001, 2, *six(0, 0, 0, 0, 0, 0)], 2),
    ("Set PR type 3", 100, [2, 3, *six(0, 0, 0, 0, 0, 0)], 2),
    ("Set TOOL[15]", 101, [15, *six(0, 0, 125.5, 0, 0, 0)], 1),
    ("Set TOOL[16]", 101, [16, *six(0, 0, 0, 0, 0, 0)], 2),
    ("Set BASE[31]", 102, [31, *six(500, -20, 0, 0, 0, 45)], 1),
    ("Set BASE[0]", 102, [0, *six(0, 0, 0, 0, 0, 0)], 2),  # Table 28: 1..31
    ("Set Current TOOL[15]", 103, [15], 1),
    ("Set Current TOOL[16]", 103, [16], 2),
    ("Set Current TOOL[-1]", 103, [u16(-1)], 2),
    ("Set Current BASE[0]", 104, [0], 1),
    ("Set Current BASE[32]", 104, [32], 2),
    ("Set HOME", 105, six(0, -90, 90, 0, 0, 0), 1),
    ("Get PR[2]", 200, [2], 1),
    ("Get PR[4001]", 200, [4001], 2),
    ("Get TOOL[0]", 201, [0], 1),
    ("Get TOOL[16]", 201, [16], 2),
    ("Get BASE[31]", 202, [31], 1),
    ("Get BASE[32]", 202, [32], 2),
    ("Get Current TOOL", 203, [], 1),
    ("Get Current BASE", 204, [], 1),
    ("Get HOME", 205, [], 1),
    ("unknown command 7", 7, [], 2),
    ("unknown command 300", 300, [], 2),
]


@pytest.fixture(scope="module")
def server() -> Iterator[SimServer]:
    with SimServer(unit=UNIT) as srv:
        yield srv


@pytest.fixture(scope="module")
def client(server: SimServer) -> Iterator[ModbusTcpClient]:
    c = ModbusTcpClient(server.host, port=server.port, timeout=3, retries=0)
    assert c.connect()
    yield c
    c.close()


def write(c: ModbusTcpClient, address: int, values: list[int]) -> None:
    rr = c.write_registers(address, values, device_id=UNIT)
    assert not rr.isError(), rr


def command(c: ModbusTcpClient, code: int, params: list[int]) -> list[int]:
    """R200 = 0, R201..R251 (unused ones zero), R200 = 1; returns IR200..IR201."""
    write(c, 200, [0])
    regs = [u16(code), *params]
    write(c, 201, regs + [0] * (51 - len(regs)))
    write(c, 200, [1])
    rr = c.read_input_registers(200, count=2, device_id=UNIT)
    assert not rr.isError(), rr
    return list(rr.registers)


def test_the_server_listens_on_loopback_at_a_free_port(server: SimServer) -> None:
    assert server.host == "127.0.0.1" and server.port > 0
    assert server.address == f"127.0.0.1:{server.port}"


@pytest.mark.parametrize(("name", "code", "params", "status"), CASES, ids=[c[0] for c in CASES])
def test_every_table_16_command_succeeds_or_fails_as_the_manual_says(
    client: ModbusTcpClient, server: SimServer, name: str, code: int, params: list[int], status: int
) -> None:
    server.call(lambda robot, now: robot.clear_fault())
    command(client, 6, [])  # Motion Stop: a motion left by the previous case must not matter
    command(client, 100, [2, 2, *six(90, 0, 0, 0, 0, 0)])  # PR[2] exists for the $PR cases
    got = command(client, code, params)
    assert got[0] == status, f"{name}: IR200 = {got[0]}"
    if code in server.robot.spec.commands:
        assert got[1] == code, f"{name}: IR201 = {got[1]}"
    write(client, 200, [0])  # JOG / GO HOME stop here


def test_table_16_cases_cover_every_command(server: SimServer) -> None:
    covered = {code for _, code, _, status in CASES if status == 1}
    assert covered == set(server.robot.spec.commands)
    refused = {code for _, code, _, status in CASES if status == 2}
    # every command with a parameter range has a failing case
    ranged = {
        code
        for code, cmd in server.robot.spec.commands.items()
        if cmd.params.select is not None
        or any(f.min is not None for lay in cmd.params.layouts for f in lay.fields)
    }
    assert ranged <= refused


#: Every parameter of Tables 17-43 that has a range, written out from the manual (not
#: from hrss_commands.toml): (case, R201, valid R202.., register, lowest, highest).
#: Point types and Set PR's type pick the layout, so their valid base is one where
#: every layout is valid (PR[1] exists, values 0.001 are fine as angles or mm).
PR1 = [1] + [0] * 11  # R203 = PR[1] (or A1 / X = 0.001), R204..R214
RANGES: list[tuple[str, int, list[int], int, int, int]] = [
    ("PTP point type (Tables 17/18)", 0, motion(2, PR1, 50), 202, 0, 2),
    *[(f"PTP joint {what} (Table 17)", 0, motion(0, JOINT90, 50, 100, 1, 2), reg, lo, hi)
      for what, reg, lo, hi in (("speed %", 215, 1, 200), ("acc %", 216, 1, 100),
                                ("TOOL", 217, 0, 15), ("BASE", 218, 0, 31),
                                ("external axis", 219, 0, 1))],
    *[(f"PTP $PR {what} (Table 18)", 0, motion(2, PR1, 50), reg, lo, hi)
      for what, reg, lo, hi in (("PR", 203, 1, 4000), ("speed %", 215, 1, 200),
                                ("acc %", 216, 1, 100), ("TOOL", 217, 0, 15),
                                ("BASE", 218, 0, 31), ("external axis", 219, 0, 1))],
    ("LIN point type (Tables 19/20)", 1, motion(2, PR1, 100), 202, 0, 2),
    *[(f"LIN Cartesian {what} (Table 19)", 1, motion(1, CART, 100), reg, lo, hi)
      for what, reg, lo, hi in (("speed mm/s", 215, 1, 6000), ("acc %", 216, 1, 100),
                                ("TOOL", 217, 0, 15), ("BASE", 218, 0, 31),
                                ("external axis", 219, 0, 1))],
    *[(f"LIN $PR {what} (Table 20)", 1, motion(2, PR1, 100), reg, lo, hi)
      for what, reg, lo, hi in (("PR", 203, 1, 4000), ("speed mm/s", 215, 1, 6000),
                                ("acc %", 216, 1, 100), ("TOOL", 217, 0, 15),
                                ("BASE", 218, 0, 31), ("external axis", 219, 0, 1))],
    *[(f"CIRC {what} (Table 21)", 2, circ(100), reg, lo, hi)
      for what, reg, lo, hi in (("speed mm/s", 226, 1, 6000), ("acc %", 227, 1, 100),
                                ("TOOL", 228, 0, 15), ("BASE", 229, 0, 31),
                                ("external axis", 230, 0, 1))],
    ("JOG axis (Table 22)", 3, [0, 1], 202, 0, 14),
    ("JOG direction (Table 22)", 3, [0, 1], 203, -1, 1),
    ("GO HOME enable (Table 23)", 4, [1], 202, 0, 1),
    ("T_STOP timer (Table 24)", 5, [1, 1], 202, 1, 20),
    ("T_STOP state (Table 24)", 5, [1, 1], 203, 0, 1),
    ("Set PR number (Table 26)", 100, [1, 1, *six(1, 2, 3, 4, 5, 6)], 202, 1, 4000),
    ("Set PR point type (Table 26)", 100, [1, 1, *six(1, 2, 3, 4, 5, 6)], 203, 0, 2),
    ("Set TOOL number (Table 27)", 101, [1, *six(0, 0, 100, 0, 0, 0)], 202, 0, 15),
    ("Set BASE number (Table 28)", 102, [1, *six(0, 0, 100, 0, 0, 0)], 202, 1, 31),
    ("Set Current TOOL (Table 29)", 103, [0], 202, 0, 15),
    ("Set Current BASE (Table 30)", 104, [0], 202, 0, 31),
    ("Get PR number (Table 32)", 200, [1], 202, 1, 4000),
    ("Get TOOL number (Table 34)", 201, [0], 202, 0, 15),
    ("Get BASE number (Table 36)", 202, [0], 202, 0, 31),
]  # fmt: skip


@pytest.mark.parametrize(
    ("name", "code", "params", "register", "lo", "hi"), RANGES, ids=[r[0] for r in RANGES]
)
def test_every_ranged_parameter_at_and_beyond_its_bounds(
    client: ModbusTcpClient,
    server: SimServer,
    name: str,
    code: int,
    params: list[int],
    register: int,
    lo: int,
    hi: int,
) -> None:
    """The manual's range of each parameter: its ends succeed (IR200 = 1), one step
    beyond fails (IR200 = 2), and a motion that fails does not move the robot."""
    server.call(lambda robot, now: robot.clear_fault())
    for value, status in ((lo - 1, 2), (lo, 1), (hi, 1), (hi + 1, 2)):
        command(client, 6, [])  # Motion Stop: nothing moves, nothing queued
        for pr in (1, 4000):  # the $PR cases move to PR[1] and PR[4000]
            assert command(client, 100, [pr, 1, *six(1, 0, 0, 0, 0, 0)])[0] == 1
        body = list(params)
        body[register - 202] = u16(value)
        got = command(client, code, body)
        assert got == [status, code], f"{name} = {value}: IR200, IR201 = {got}"
        if status == 2 and code in (0, 1, 2, 3, 4):
            rr = client.read_input_registers(524, count=1, device_id=UNIT)
            assert rr.registers == [1], f"{name} = {value} failed but the robot moves"
        write(client, 200, [0])  # JOG / GO HOME stop here


def test_the_ranges_above_are_every_range_the_command_data_has(server: SimServer) -> None:
    """Nothing in hrss_commands.toml has a range the manual-written table above misses,
    and the two agree on every bound."""
    from_manual = {(code, reg, lo, hi) for _n, code, _p, reg, lo, hi in RANGES}
    from_data = set()
    for code, cmd in server.robot.spec.commands.items():
        fields = [f for lay in cmd.params.layouts for f in lay.fields]
        if cmd.params.select is not None:
            fields.append(cmd.params.select)
        from_data |= {(code, f.reg, f.min, f.max) for f in fields if f.min is not None}
    assert from_data == from_manual


def test_more_than_8000_queued_motions_fail_other_commands_do_not() -> None:
    """Table 15: with 8000 commands waiting, a motion command fails; IR102 counts them."""
    from mbmon.sim.robot import SimRobot

    robot = SimRobot()
    H = "holding_registers"
    assert robot.write(H, 201, [0, *motion(0, JOINT90, 1)], 0.0) is None
    for i in range(8001):  # one runs, 8000 wait (the parameters stay in R201..)
        robot.write(H, 200, [0], 0.0)
        robot.write(H, 200, [1], 0.0)
        assert robot.status == 1, i
    assert robot.read("input_registers", 102, 1, 0.0) == [8000]
    robot.write(H, 200, [0], 0.0)
    robot.write(H, 200, [1], 0.0)
    assert robot.status == 2
    assert robot.read("input_registers", 102, 1, 0.0) == [8000]
    robot.write(H, 200, [0], 0.0)
    robot.write(H, 201, [103, 5], 0.0)
    robot.write(H, 200, [1], 0.0)
    assert robot.status == 1 and robot.current_tool == 5


def test_get_returns_decode_with_the_analyzers_own_layouts(client: ModbusTcpClient) -> None:
    assert command(client, 101, [4, *six(1, 2, 3, 4, 5, 6)])[0] == 1
    assert command(client, 201, [4])[0] == 1
    rr = client.read_input_registers(202, count=13, device_id=UNIT)
    image = {202 + i: v for i, v in enumerate(rr.registers)}
    dec = decode_returns(201, image)
    assert dec is not None and dec.text == "TOOL[4] = {X 1, Y 2, Z 3, A 4, B 5, C 6}"
    assert command(client, 100, [12, 1, *six(10, -20, 30.5, 0, 0, 0)])[0] == 1
    assert command(client, 200, [12])[0] == 1
    rr = client.read_input_registers(202, count=14, device_id=UNIT)
    dec = decode_returns(200, {202 + i: v for i, v in enumerate(rr.registers)})
    assert dec is not None and dec.text == "PR[12] = {A1 10, A2 -20, A3 30.5, A4 0, A5 0, A6 0}"


def test_reads_and_writes_outside_the_map_answer_exception_02(client: ModbusTcpClient) -> None:
    for rr in (
        client.read_coils(256, count=1, device_id=UNIT),
        client.read_coils(550, count=7, device_id=UNIT),
        client.read_discrete_inputs(250, count=10, device_id=UNIT),
        client.read_input_registers(300, count=112, device_id=UNIT),
        client.read_holding_registers(1950, count=1, device_id=UNIT),
        client.write_register(101, 1, device_id=UNIT),
        client.write_coil(256, True, device_id=UNIT),
    ):
        assert rr.isError() and rr.exception_code == 2, rr
    rr = client.read_coils(550, count=6, device_id=UNIT)  # DO[251]..DO[256]: inside
    assert not rr.isError()


def test_set_speed_outside_1_100_answers_exception_03(client: ModbusTcpClient) -> None:
    rr = client.write_register(100, 0, device_id=UNIT)
    assert rr.isError() and rr.exception_code == 3
    rr = client.write_registers(200, [2], device_id=UNIT)
    assert rr.isError() and rr.exception_code == 3


def test_function_codes_outside_table_10_answer_exception_01(client: ModbusTcpClient) -> None:
    rr = client.readwrite_registers(
        read_address=200, read_count=1, write_address=201, values=[0], device_id=UNIT
    )
    assert rr.isError() and rr.exception_code == 1
    rr = client.mask_write_register(address=201, and_mask=0xFFFF, or_mask=0, device_id=UNIT)
    assert rr.isError() and rr.exception_code == 1


def test_another_unit_on_tcp_answers_exception_0b(client: ModbusTcpClient) -> None:
    rr = client.read_input_registers(100, count=1, device_id=UNIT + 1)
    assert rr.isError() and rr.exception_code == 0x0B


def test_single_coil_and_register_writes_fc05_fc06(
    client: ModbusTcpClient, server: SimServer
) -> None:
    assert not client.write_coil(300 + 7, True, device_id=UNIT).isError()  # DO[8]
    assert client.read_coils(307, count=1, device_id=UNIT).bits[0] is True
    assert not client.write_register(100, 35, device_id=UNIT).isError()
    assert client.read_input_registers(100, count=1, device_id=UNIT).registers == [35]
    assert server.snapshot()["speed_pct"] == 35
    assert not client.write_register(100, 100, device_id=UNIT).isError()


def test_start_on_a_busy_port_raises_oserror(server: SimServer) -> None:
    other = SimServer(port=server.port)
    with pytest.raises(OSError):
        other.start()
    other.stop()


def a1(c: ModbusTcpClient) -> float:
    rr = c.read_input_registers(300, count=2, device_id=UNIT)
    low, high = rr.registers
    return (u16(high) - (0x10000 if high & 0x8000 else 0)) * 65536 + low


def test_jog_moves_while_r200_stays_1_and_stops_when_it_is_cleared(
    client: ModbusTcpClient,
) -> None:
    command(client, 6, [])
    write(client, 200, [0])
    start = a1(client)
    t0 = time.monotonic()
    assert command(client, 3, [0, 1]) == [1, 3]  # JOG A1 + (Example 5)
    assert client.read_input_registers(524, count=1, device_id=UNIT).registers == [2]
    time.sleep(0.3)
    moving = a1(client)
    assert moving > start
    time.sleep(0.3)
    later = a1(client)
    assert later > moving
    assert client.read_input_registers(524, count=1, device_id=UNIT).registers == [2]
    write(client, 200, [0])  # released
    elapsed = time.monotonic() - t0
    stopped = a1(client)
    # 10 deg/s at 100 % override: never more than the time R200 stayed 1 allows
    assert stopped - start <= 10_000 * elapsed + 1
    assert client.read_input_registers(524, count=1, device_id=UNIT).registers == [1]
    time.sleep(0.3)
    assert a1(client) == stopped
