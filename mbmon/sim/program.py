"""The manual's §5.4.5.2 client program (robot A drives robot B), plus LIN, Set/Get PR and JOG.

What it owns: one HRSS client session as a list of Modbus requests, run step by
step with a pymodbus client against any HRSS-like server (``mbmon sim``, a
proxy in front of it, a real controller). Every request is reported to an
``on_step`` callback as a :class:`Step` once it is answered; each part after
§5.4.5.2 (``LIN``, ``Set PR``, ...) is announced to ``on_part`` before its
first request is sent.

The §5.4.5.2 part follows the program line by line (lines 4-42): read B's
speed (IR100), set it to 90 % (R100), read DI[1]..DI[8], write DO[1]..DO[5],
reset R200, write the PTP parameters R201..R226 (Table 46: PTP {A1 90} Vel=50%
Acc=100% TOOL[1] BASE[2]), R200 = 1, then poll IR524 every 0.1 s while it reads
2 (Running). As in docs/commands.md (choice 8), program addresses are wire
addresses and MBC_WRITE_HOLDING sends FC 0x10 even for one word. The extras
are the manual's Examples 4, 7, 8 and 5 (Tables 47, 50, 52, 48), each with the
R200 reset first and the IR200 status read after the execute:

* LIN {X -300, Y 300, Z 400, A 180, B 0, C 90} Vel=1000mm/s Acc=100% TOOL[3] BASE[7]
  (Table 47 as Table 19 reads it: R201 = 1, R202 = 1), polled until Idle, then
  the Cartesian position IR400..IR411 read back (where the LIN ended);
* $PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0} (Set PR), then Get PR[2] with IR202..IR215;
* JOG A1 + for ``jog_seconds`` while R200 stays 1, then R200 = 0 stops it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from mbmon.sim.spec import join_i32, split_i32, u16

__all__ = ["ProgramError", "ProgramResult", "Step", "run_program", "words_i32"]


@dataclass(frozen=True, slots=True)
class Step:
    """One answered request of the program.

    ``index`` counts from 1; ``part`` is the program part (``5.4.5.2``,
    ``LIN``, ``Set PR``, ``Get PR``, ``JOG``); ``line`` the program statement
    (MBC_* call of the manual, or its equivalent); ``text`` what it does in
    words; ``function`` the Modbus function code; ``address``/``values`` what
    was asked or written; ``result`` the registers or bits read (``None`` for
    writes); ``started``/``ended`` wall-clock times around the request.
    """

    index: int
    part: str
    line: str
    text: str
    function: int
    address: int
    values: tuple[int, ...]
    result: tuple[int, ...] | None
    started: float
    ended: float


class ProgramError(RuntimeError):
    """A request failed (no answer, an exception response) or the robot never finished."""


@dataclass(slots=True)
class ProgramResult:
    """What the program saw: every step, and the values it kept ($C[n] of the manual)."""

    steps: list[Step] = field(default_factory=list)
    speed_before: int | None = None  # $C[1]: IR100 before the write
    di: tuple[int, ...] = ()  # $C[2..9]: DI[1]..DI[8]
    joints: tuple[float, ...] = ()  # A1..A6 (degrees) read after the PTP
    pose: tuple[float, ...] = ()  # X..C (mm, degrees) read after the LIN
    statuses: dict[str, int] = field(default_factory=dict)  # IR200 after each extra command
    pr2: tuple[int, ...] = ()  # IR202..IR215 after Get PR[2]
    jog_from: float = 0.0  # A1 (degrees) read just before the JOG's R200 = 1
    jog_to: float = 0.0  # A1 read once the JOG had stopped (R200 = 0, IR524 not Running)
    jog_moved: float = 0.0  # jog_to - jog_from: the whole JOG, start to standstill
    jog_after_stop: float = 0.0  # degrees A1 moved in the 0.3 s after R200 = 0


def words_i32(value: float) -> list[int]:
    """(low, high) unsigned words of ``value`` in 0.001 units (Appendix II): 90 -> [24464, 1]."""
    low, high = split_i32(round(value * 1000))
    return [u16(low), u16(high)]


def _ptp_params() -> list[int]:
    """R201..R226 of Table 46 (the program's WRITE_DATA[1..26], lines 28-35)."""
    data = [0] * 26
    data[0], data[1] = 0, 0  # PTP, joint point type
    data[2], data[3] = 24464, 1  # A1 = 90 degrees
    data[14], data[15], data[16], data[17] = 50, 100, 1, 2  # Vel, Acc, TOOL, BASE
    return data


def _lin_params() -> list[int]:
    """R201..R226 of Example 4 (Table 47 read as Table 19 says: LIN, Cartesian)."""
    data = [1, 1]
    for v in (-300, 300, 400, 180, 0, 90):
        data += words_i32(v)
    data += [1000, 100, 3, 7, 0] + [0] * 7
    return data


def _set_pr_params() -> list[int]:
    """R201..R215 of Example 7 (Table 50): $PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0}."""
    data = [100, 2, 2]
    for v in (90, 0, 0, 0, 0, 0):
        data += words_i32(v)
    return data


class _Runner:
    def __init__(
        self, client: Any, unit: int, on_step: Callable[[Step], None] | None, result: ProgramResult
    ) -> None:
        self.client, self.unit, self.on_step, self.result = client, unit, on_step, result
        self.part = "5.4.5.2"
        self.on_part: Callable[[str], None] | None = None

    def begin(self, part: str) -> None:
        """A new part of the program: named in the steps, told to ``on_part`` first."""
        self.part = part
        if self.on_part is not None:
            self.on_part(part)

    def _done(
        self,
        fc: int,  # the code the answer carries (pymodbus's call picks it)
        line: str,
        text: str,
        address: int,
        values: Sequence[int],
        got: tuple[int, ...] | None,
        started: float,
    ) -> None:
        n = len(self.result.steps) + 1
        step = Step(n, self.part, line, text, fc, address, tuple(values), got, started, time.time())
        self.result.steps.append(step)
        if self.on_step is not None:
            self.on_step(step)

    def _check(self, rr: Any, line: str) -> Any:
        if rr is None or rr.isError():
            raise ProgramError(f"{self.part}: {line}: {rr}")
        return rr

    def read_input(self, address: int, count: int, line: str, text: str) -> tuple[int, ...]:
        t = time.time()
        try:
            rr = self.client.read_input_registers(address, count=count, device_id=self.unit)
        except Exception as exc:  # pymodbus raises ModbusException on no answer
            raise ProgramError(f"{self.part}: {line}: {exc}") from exc
        got = tuple(self._check(rr, line).registers[:count])
        self._done(rr.function_code, line, text, address, (count,), got, t)
        return got

    def read_dinput(self, address: int, count: int, line: str, text: str) -> tuple[int, ...]:
        t = time.time()
        try:
            rr = self.client.read_discrete_inputs(address, count=count, device_id=self.unit)
        except Exception as exc:
            raise ProgramError(f"{self.part}: {line}: {exc}") from exc
        got = tuple(int(b) for b in self._check(rr, line).bits[:count])
        self._done(rr.function_code, line, text, address, (count,), got, t)
        return got

    def write_holding(self, address: int, values: Sequence[int], line: str, text: str) -> None:
        t = time.time()
        try:
            rr = self.client.write_registers(address, list(values), device_id=self.unit)
        except Exception as exc:
            raise ProgramError(f"{self.part}: {line}: {exc}") from exc
        self._check(rr, line)
        self._done(rr.function_code, line, text, address, values, None, t)

    def write_coil(self, address: int, bits: Sequence[int], line: str, text: str) -> None:
        t = time.time()
        try:
            rr = self.client.write_coils(address, [bool(b) for b in bits], device_id=self.unit)
        except Exception as exc:
            raise ProgramError(f"{self.part}: {line}: {exc}") from exc
        self._check(rr, line)
        self._done(rr.function_code, line, text, address, bits, None, t)

    def execute(
        self, params: Sequence[int], what: str, before_start: Callable[[], Any] | None = None
    ) -> None:
        """R200 = 0, parameters from R201, R200 = 1 (the handshake of §5.3.3.5);
        ``before_start`` runs just before R200 = 1 (nothing moves until then)."""
        n = len(params)
        self.write_holding(200, [0], "MBC_WRITE_HOLDING(1,200,WRITE_DATA,'W',1)", "R200 = 0")
        self.write_holding(
            201, params, f"MBC_WRITE_HOLDING(1,201,WRITE_DATA,'W',{n})", f"{what}: R201..R{200 + n}"
        )
        if before_start is not None:
            before_start()
        self.write_holding(200, [1], "MBC_WRITE_HOLDING(1,200,WRITE_DATA,'W',1)", "R200 = 1")

    def wait_idle(self, poll: float, timeout: float) -> None:
        """Lines 39-42: read IR524, and again every ``poll`` s while it is 2 (Running)."""
        line = "MBC_READ_INPUT(1,524,READ_DATA,'W',1)"
        state = self.read_input(524, 1, line, "IR524 motion state")[0]
        deadline = time.monotonic() + timeout
        while state == 2:
            if time.monotonic() > deadline:
                raise ProgramError(f"{self.part}: still Running after {timeout} s")
            state = self.read_input(524, 1, line, "IR524 motion state")[0]
            time.sleep(poll)

    def status(self, what: str) -> int:
        s = self.read_input(200, 1, "MBC_READ_INPUT(1,200,READ_DATA,'W',1)", "IR200 status")[0]
        self.result.statuses[what] = s
        return s

    def a1(self) -> float:
        w = self.read_input(300, 2, "MBC_READ_INPUT(1,300,READ_DATA,'W',2)", "IR300..IR301 A1")
        return join_i32(w[0], w[1]) / 1000


def run_program(
    host: str = "127.0.0.1",
    port: int = 502,
    *,
    unit: int = 1,
    client: Any = None,
    on_step: Callable[[Step], None] | None = None,
    on_part: Callable[[str], None] | None = None,
    poll: float = 0.1,
    timeout: float = 30.0,
    jog_seconds: float = 0.5,
    extras: bool = True,
) -> ProgramResult:
    """Run the §5.4.5.2 program (and, with ``extras``, LIN, Set/Get PR, JOG) against a server.

    Connects a pymodbus ``ModbusTcpClient`` to ``host:port`` unless ``client``
    (any connected pymodbus sync client, e.g. a ``ModbusSerialClient`` for RTU)
    is given; a client made here is closed at the end. ``on_step(step)`` follows
    each answered request, ``on_part(name)`` precedes each extra part. Raises
    :class:`ProgramError` when a request fails or a motion outlasts ``timeout``.
    """
    own = client is None
    if own:
        from pymodbus.client import ModbusTcpClient

        client = ModbusTcpClient(host, port=port, timeout=3, retries=0)
        if not client.connect():
            raise ProgramError(f"cannot connect to {host}:{port}")
    result = ProgramResult()
    r = _Runner(client, unit, on_step, result)
    r.on_part = on_part
    try:
        # lines 4-5: $C[1] = B's speed
        result.speed_before = r.read_input(
            100, 1, "MBC_READ_INPUT(1,100,READ_DATA,'W',1)", "IR100 speed %"
        )[0]
        # lines 6-7: B's speed = 90 %
        r.write_holding(100, [90], "MBC_WRITE_HOLDING(1,100,WRITE_DATA,'W',1)", "R100 = 90 %")
        # lines 8-16: $C[2..9] = DI[1..8]
        result.di = r.read_dinput(300, 8, "MBC_READ_DINPUT(1,300,READ_DATA,8)", "DI[1]..DI[8]")
        # lines 17-22: DO[1..5] = 1, 1, 0, 0, 1
        r.write_coil(
            300, [1, 1, 0, 0, 1], "MBC_WRITE_COIL(1,300,WRITE_DATA,5)", "DO[1]..DO[5] = 1 1 0 0 1"
        )
        # lines 23-36: R200 = 0, PTP parameters in R201..R226; 37-38: R200 = 1
        r.execute(_ptp_params(), "PTP {A1 90} Vel=50% Acc=100% TOOL[1] BASE[2]")
        # lines 39-42: poll IR524 while Running
        r.wait_idle(poll, timeout)
        joints = r.read_input(
            300, 12, "MBC_READ_INPUT(1,300,READ_DATA,'W',12)", "IR300..IR311 A1..A6"
        )
        result.joints = tuple(join_i32(joints[i], joints[i + 1]) / 1000 for i in range(0, 12, 2))
        if extras:
            _extras(r, result, poll, timeout, jog_seconds)
    finally:
        if own:
            client.close()
    return result


def _extras(
    r: _Runner, result: ProgramResult, poll: float, timeout: float, jog_seconds: float
) -> None:
    r.begin("LIN")
    r.execute(_lin_params(), "LIN {X -300, Y 300, Z 400, A 180, B 0, C 90} Vel=1000mm/s")
    r.status("LIN")
    r.wait_idle(poll, timeout)
    pose = r.read_input(400, 12, "MBC_READ_INPUT(1,400,READ_DATA,'W',12)", "IR400..IR411 X..C")
    result.pose = tuple(join_i32(pose[i], pose[i + 1]) / 1000 for i in range(0, 12, 2))

    r.begin("Set PR")
    r.execute(_set_pr_params(), "$PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0}")
    r.status("Set PR")

    r.begin("Get PR")
    r.execute([200, 2], "Get PR[2]")
    got = r.read_input(
        200, 16, "MBC_READ_INPUT(1,200,READ_DATA,'W',16)", "IR200..IR215 status, action, PR[2]"
    )
    result.statuses["Get PR"] = got[0]
    result.pr2 = got[2:]

    # JOG moves from R200 = 1 until R200 returns to 0 (Table 22, Example 5): what it
    # moved is measured from the pose before R200 = 1 to the pose once it stopped
    r.begin("JOG")
    start: list[float] = []
    r.execute([3, 0, 1], "JOG A1 +", before_start=lambda: start.append(r.a1()))
    r.status("JOG")
    time.sleep(jog_seconds)
    r.write_holding(200, [0], "MBC_WRITE_HOLDING(1,200,WRITE_DATA,'W',1)", "R200 = 0 stops JOG")
    stopped = r.a1()
    time.sleep(0.3)
    r.wait_idle(poll, timeout)
    later = r.a1()
    result.jog_from, result.jog_to = start[0], later
    result.jog_moved = later - start[0]
    result.jog_after_stop = later - stopped
