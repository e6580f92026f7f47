"""SimRobot: the HRSS controller's Modbus face as a pure state machine (time is an input).

What it owns: the four register tables of the manual's chapter 5.3.3 (Tables
12-15, addresses from the ``hrss`` profile), the command handshake of
§5.3.3.5 (parameters in R201..R251, a 0 -> 1 edge of R200 executes, IR200
status, IR201 action, IR101 custom code, IR102 queue), every command of Table
16 with the parameter ranges of ``hrss_commands.toml`` (out of range -> IR200 =
2), motion over time (linear interpolation at the commanded speed, circular
arcs for CIRC; no kinematics: joint targets move A1..A6, Cartesian targets move
X..C, and the other set stays where it is), JOG and GO HOME that run while
R200 stays 1, position registers (PR[1..50] live in R1000..R1949), TOOL, BASE,
HOME, Timer and Counter registers, and SO1..SO4 (Run, Held, Fault, Ready).

It never reads a clock: every entry point takes ``now`` (seconds, any
monotonic origin), and :meth:`SimRobot.step` moves the state to that time. It
does no I/O and is not thread-safe (:class:`~mbmon.sim.server.SimServer` locks
around it). Words are unsigned 16-bit values on the way in and out; 32-bit
values are stored low word first (manual Appendix II, docs/registers.md).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from mbmon.sim.motion import Motion, MotionState, jog_rate, position, start_motion
from mbmon.sim.spec import (
    CommandField,
    Layout,
    Spec,
    address_map,
    command_spec,
    decode_command,
    join_i32,
    plan,
    s16,
    split_i32,
    u16,
)
from mbmon.sim.timers import Timers

__all__ = [
    "EXC_ILLEGAL_ADDRESS",
    "EXC_ILLEGAL_VALUE",
    "MotionState",
    "SimEvent",
    "SimRobot",
]

#: Modbus exception codes the robot answers with.
EXC_ILLEGAL_ADDRESS = 2
EXC_ILLEGAL_VALUE = 3

# Every address comes from the data (profiles/hrss.toml, hrss_commands.toml): see spec.Plan.
_P = plan()
IR_SPEED, IR_CODE, IR_QUEUE = _P.speed, _P.code, _P.queue
IR_STATUS, IR_ACTION, IR_RETURNS, IR_RETURNS_END = _P.status, _P.action, _P.returns, _P.returns_end
IR_JOINTS, IR_POSE = _P.joints, _P.pose
IR_DRIVE_ERROR, IR_HRSS_ERROR = _P.drive_error, _P.hrss_error
IR_TCP_SPEED, IR_EXCITED, IR_ACC_TIME, IR_MOTION = _P.tcp_speed, _P.excited, _P.acc_time, _P.motion
R_SPEED, R_EXECUTE, R_COMMAND, R_PARAMS_END = _P.set_speed, _P.execute, _P.command, _P.params_end
R_TIMER, TIMER_STRIDE, TIMERS = _P.timer, _P.timer_stride, _P.timers
R_PR, PR_WORDS, PR_IN_REGISTERS = _P.pr, _P.pr_stride, _P.prs
SO_RUN, SO_HELD, SO_FAULT, SO_READY = (_P.so + i for i in range(4))  # SO1..SO4
SI_HOLD, SI_STOP = _P.si + 1, _P.si + 2  # SI2 Hold, SI3 Stop
DI_BASE, DO_BASE = _P.di - 1, _P.do - 1  # DI[n] / DO[n] at 299+n
SO_BASE = _P.so - 1  # SO[n] at n-1
SRW_BASE = 0  # SRW[n] at n-1 (IR0..IR31)

QUEUE_MAX = _P.queue_max  # Table 15: more than 8000 waiting -> motion commands fail
DEFAULT_HOME = (0.0, 0.0, 0.0, 0.0, -90.0, 0.0)
DEFAULT_POSE = (400.0, 0.0, 500.0, 180.0, 0.0, 0.0)
DEFAULT_DI = (1, 3)  # DI[1] and DI[3] on, so a first read shows something


@dataclass(slots=True)
class SimEvent:
    """Something the robot did, for the console and tests: ``text`` says it in words."""

    ts: float
    kind: str  # "execute" | "motion" | "stop" | "ignored" | "write-rejected"
    text: str
    ok: bool = True


class SimRobot:
    """The simulated HRSS controller. See the module docstring for what it models.

    ``joint_speed`` is the joint speed (deg/s) at 100 % PTP speed and 100 %
    override (R100); ``cart_speed`` the linear speed (mm/s) of a Cartesian PTP
    at 100 %; ``rot_speed`` the orientation speed (deg/s) at 100 %.
    ``on_event`` receives :class:`SimEvent` records (executes, motion ends).
    """

    def __init__(
        self,
        now: float = 0.0,
        *,
        joint_speed: float = 180.0,
        cart_speed: float = 1000.0,
        rot_speed: float = 180.0,
        spec: Spec | None = None,
        on_event: Callable[[SimEvent], None] | None = None,
    ) -> None:
        self.spec = spec or command_spec()
        self.map = address_map()
        self.joint_speed = joint_speed
        self.cart_speed = cart_speed
        self.rot_speed = rot_speed
        self.on_event = on_event
        self.now = now
        self.coils = [0] * _P.sizes["coils"]
        self.discrete = [0] * _P.sizes["discrete_inputs"]
        for n in DEFAULT_DI:
            self.discrete[DI_BASE + n] = 1
        self.holding = [0] * _P.sizes["holding_registers"]
        self.holding[R_SPEED] = 100
        # inputs: SRW, IR200, IR201 and the returns are stored; the rest is refreshed on read
        self.inputs = [0] * _P.sizes["input_registers"]
        self.joints = [0.0, 0.0, 0.0, 0.0, -90.0, 0.0]
        self.pose = list(DEFAULT_POSE)
        self.ext = [0.0, 0.0, 0.0]
        self.tools: dict[int, tuple[int, ...]] = {}
        self.bases: dict[int, tuple[int, ...]] = {}
        self.home: tuple[int, ...] = tuple(round(v * 1000) for v in DEFAULT_HOME)
        self.current_tool = 0
        self.current_base = 0
        self.far_prs: dict[int, tuple[int, tuple[int, ...]]] = {}  # PR[51..4000]
        self.motion: Motion | None = None
        self.queue: deque[Motion] = deque()
        self.held = False
        self.fault = 0  # HRSS error code (IR502..IR503); non-zero = Fault
        self.acc_ms = 200
        self.timers = Timers(self.holding, R_TIMER, TIMER_STRIDE, TIMERS)
        self.executed = 0  # commands executed (R200 edges), for tests and the console
        self.event_error: Exception | None = None  # why on_event was detached, if it was

    # ------------------------------------------------------------------ Modbus face

    def check(self, table: str, address: int, count: int) -> int | None:
        """``None`` when the addresses lie in one range of the map, else exception 02."""
        end = address + count
        for start, stop in self.map[table]:
            if start <= address and end <= stop:
                return None
        return EXC_ILLEGAL_ADDRESS

    def read(self, table: str, address: int, count: int, now: float) -> list[int] | int:
        """Values of ``count`` addresses (bits as 0/1, words unsigned), or an exception code."""
        exc = self.check(table, address, count)
        if exc is not None:
            return exc
        self.step(now)
        return self.table(table)[address : address + count]

    def write(self, table: str, address: int, values: Sequence[int], now: float) -> int | None:
        """Apply a client write (coils or holding registers); an exception code refuses it whole.

        R100 (set speed) accepts 1..100 and R200 0..1, else exception 03; other
        registers take any word. A 0 -> 1 edge of R200 executes the command in
        R201..R251 after every word of the request is stored.
        """
        if table not in ("coils", "holding_registers"):
            return EXC_ILLEGAL_ADDRESS
        exc = self.check(table, address, len(values))
        if exc is not None:
            return exc
        self.step(now)
        if table == "coils":
            self._write_coils(address, [1 if v else 0 for v in values])
            return None
        words = [u16(int(v)) for v in values]
        for i, w in enumerate(words):
            reg = address + i
            if reg == R_SPEED and not 1 <= s16(w) <= 100:
                self._event("write-rejected", f"R100 = {s16(w)} outside 1..100", ok=False)
                return EXC_ILLEGAL_VALUE
            if reg == R_EXECUTE and w not in (0, 1):
                self._event("write-rejected", f"R200 = {s16(w)} outside 0..1", ok=False)
                return EXC_ILLEGAL_VALUE
        before = self.holding[R_EXECUTE]
        self.holding[address : address + len(words)] = words
        self.timers.written(address, address + len(words), self.now)
        after = self.holding[R_EXECUTE]
        if address <= R_EXECUTE < address + len(words):
            if before != 1 and after == 1:
                self.execute()
            elif before == 1 and after == 1:
                self._event(
                    "ignored", "R200 = 1 again without R200 = 0 first: nothing executed", ok=False
                )
            elif before == 1 and after == 0:
                self._r200_reset()
        return None

    def table(self, table: str) -> list[int]:
        """The whole live image of ``table`` (index = address), SO bits and inputs refreshed.

        For a server that mirrors the robot into a store of its own; call
        :meth:`step` first. The list is the robot's own: do not modify it.
        """
        if table == "coils":
            return self.coils
        if table == "discrete_inputs":
            self._publish_so()
            return self.discrete
        if table == "holding_registers":
            return self.holding
        self._publish_inputs()
        return self.inputs

    # ------------------------------------------------------------------ time

    def step(self, now: float) -> None:
        """Move the state to ``now`` (earlier times are ignored): motion, timers."""
        dt = now - self.now
        if dt <= 0:
            return
        self.now = now
        left = dt
        while self.motion is not None and not self.held and left > 0:
            m = self.motion
            if m.jog is not None:
                self._jog(m, left)
                left = 0.0
                break
            need = m.duration - m.elapsed
            if left < need:
                m.elapsed += left
                self._place(m)
                left = 0.0
                break
            m.elapsed = m.duration
            self._place(m)
            left -= need
            self._finish(now - left)
        self.timers.publish(self.now)

    # ------------------------------------------------------------------ convenience API

    @property
    def motion_state(self) -> int:
        """IR524: Idle, Running or Hold."""
        if self.motion is None:
            return MotionState.IDLE
        return MotionState.HOLD if self.held else MotionState.RUNNING

    @property
    def status(self) -> int:
        """IR200 of the last command: 0 Ready (none yet), 1 Success, 2 Fail."""
        return self.inputs[IR_STATUS]

    def set_di(self, n: int, value: bool) -> None:
        """Set digital input DI[n] (1..256), which clients read at discrete input 299+n."""
        if not 1 <= n <= 256:
            raise ValueError(f"DI[{n}]: n must be 1..256")
        self.discrete[DI_BASE + n] = 1 if value else 0

    def set_so(self, n: int, value: bool) -> None:
        """Set a user output SO[n] (5..256); SO1..SO4 follow the robot state."""
        if not 5 <= n <= 256:
            raise ValueError(f"SO{n}: n must be 5..256 (SO1..SO4 follow the state)")
        self.discrete[SO_BASE + n] = 1 if value else 0

    def set_srw(self, n: int, value: int) -> None:
        """Set fieldbus register SRW[n] (1..32), input register n-1."""
        if not 1 <= n <= 32:
            raise ValueError(f"SRW[{n}]: n must be 1..32")
        self.inputs[SRW_BASE + n - 1] = u16(value)

    def set_fault(self, code: int, now: float | None = None) -> None:
        """Raise an HRSS error: IR502..IR503 = ``code``, SO3 Fault, motion stops, motions fail."""
        if now is not None:
            self.step(now)
        self.fault = code & 0xFFFFFFFF or 1
        self._stop_all("fault")

    def clear_fault(self) -> None:
        """Clear the HRSS error (IR502..IR503 = 0, SO4 Ready again)."""
        self.fault = 0

    def pr(self, n: int) -> tuple[int, tuple[int, ...]]:
        """PR[n] as (type 0/1/2, nine raw values in 0.001 units)."""
        if n <= PR_IN_REGISTERS:
            base = R_PR + PR_WORDS * (n - 1)
            regs = self.holding
            values = tuple(
                join_i32(regs[base + 1 + 2 * i], regs[base + 2 + 2 * i]) for i in range(9)
            )
            return s16(regs[base]), values
        return self.far_prs.get(n, (0, (0,) * 9))

    def state(self) -> dict[str, Any]:
        """A plain snapshot: joints, pose (floats), motion state, status, queue, speeds."""
        self._publish_inputs()
        return {
            "joints": tuple(self.joints),
            "pose": tuple(self.pose),
            "ext": tuple(self.ext),
            "motion_state": self.motion_state,
            "status": self.status,
            "action": s16(self.inputs[IR_ACTION]),
            "queue": len(self.queue),
            "speed_pct": s16(self.holding[R_SPEED]),
            "tcp_speed": join_i32(self.inputs[IR_TCP_SPEED], self.inputs[IR_TCP_SPEED + 1]) / 1000,
            "tool": self.current_tool,
            "base": self.current_base,
            "fault": self.fault,
            "executed": self.executed,
        }

    # ------------------------------------------------------------------ commands

    def execute(self) -> None:
        """Run the command in R201..R251 now (what a 0 -> 1 edge of R200 does)."""
        self.executed += 1
        image = {a: self.holding[a] for a in range(R_COMMAND, R_PARAMS_END)}
        dec = decode_command(image, self.spec)
        cmd = self.spec.commands.get(dec.code) if dec.code is not None else None
        if cmd is not None:
            self.inputs[IR_ACTION] = u16(cmd.code)
        problems = list(dec.problems)
        if not problems and cmd is not None and dec.layout is not None:
            raws = {f.name: raw for f in dec.layout.fields if (raw := f.raw(image.get)) is not None}
            sel = cmd.params.select
            if sel is not None:
                raw_sel = sel.raw(image.get)
                if raw_sel is not None:
                    raws[sel.name] = raw_sel
            handler = _HANDLERS.get(cmd.code)
            reason = handler(self, dec.text, raws) if handler else "not modelled"
            if reason:
                problems.append(reason)
        ok = not problems
        self.inputs[IR_STATUS] = 1 if ok else 2
        text = dec.text + ("" if ok else f": {'; '.join(problems)}")
        self._event("execute", ("success: " if ok else "fail: ") + text, ok=ok)

    def _r200_reset(self) -> None:
        m = self.motion
        if m is not None and (m.jog is not None or m.hold_to_run):
            self.motion = None
            self._event("stop", f"{m.command} stopped (R200 = 0)")
            self._start_next()

    # handlers: return None on success, or why the command fails (IR200 = 2)

    def _cmd_move(self, text: str, p: Mapping[str, int], *, linear: bool) -> str | None:
        if self.fault:
            return "robot in fault"
        if len(self.queue) >= QUEUE_MAX:
            return f"more than {QUEUE_MAX} commands queued"
        point = p["point_type"]
        ext = [p.get(f"E{i}", 0) / 1000 for i in (1, 2, 3)] if p.get("ext") else None
        if point == 2:
            pr_type, values = self.pr(p["pr"])
            if pr_type not in (1, 2):
                return f"PR[{p['pr']}] is {'NULL' if pr_type == 0 else f'type {pr_type}'}"
            space = "joint" if pr_type == 1 else "cart"
            six = [v / 1000 for v in values[:6]]
            if ext is None and pr_type == 2:
                ext = [v / 1000 for v in values[6:9]]
        else:
            space = "joint" if point == 0 else "cart"
            names = ("A1", "A2", "A3", "A4", "A5", "A6") if point == 0 else "XYZABC"
            six = [p[n] / 1000 for n in names]
        speed = p["speed"] if linear else p["speed"] / 100
        self._set_acc(p["acc"])
        self._queue(
            Motion(
                command=text,
                space=space,
                target=(*six, *(ext if ext is not None else self.ext)),
                speed=speed,
                linear=linear,
                code=p.get("code", 0),
            )
        )
        return None

    def _cmd_circ(self, text: str, p: Mapping[str, int]) -> str | None:
        if self.fault:
            return "robot in fault"
        if len(self.queue) >= QUEUE_MAX:
            return f"more than {QUEUE_MAX} commands queued"
        aux = tuple(p[n] / 1000 for n in ("X1", "Y1", "Z1", "A1", "B1", "C1"))
        end = tuple(p[n] / 1000 for n in ("X2", "Y2", "Z2", "A2", "B2", "C2"))
        ext = [p.get(f"E{i}", 0) / 1000 for i in (1, 2, 3)] if p.get("ext") else list(self.ext)
        self._set_acc(p["acc"])
        self._queue(
            Motion(
                command=text,
                space="cart",
                target=(*end, *ext),
                speed=p["speed"],
                linear=True,
                code=p.get("code", 0),
                aux=aux,
            )
        )
        return None

    def _cmd_jog(self, text: str, p: Mapping[str, int]) -> str | None:
        if self.fault:
            return "robot in fault"
        if self.motion is not None:
            return "robot is moving"
        if p["dir"] == 0:
            return None
        self.motion = Motion(
            command=text, space="jog", target=(), speed=0, linear=False, jog=(p["axis"], p["dir"])
        )
        rate = jog_rate(p["axis"], self._override)
        self.motion.tcp_speed = rate if p["axis"] in range(6, 9) else 0.0
        return None

    def _cmd_home(self, text: str, p: Mapping[str, int]) -> str | None:
        if p["enable"] == 0:
            m = self.motion
            if m is not None and m.hold_to_run:
                self.motion = None
                self._start_next()
            return None
        if self.fault:
            return "robot in fault"
        if self.motion is not None:
            return "robot is moving"
        self._queue(
            Motion(
                command=text,
                space="joint",
                target=(*(v / 1000 for v in self.home), *self.ext),
                speed=0.2,
                linear=False,
                hold_to_run=True,
            )
        )
        return None

    def _cmd_t_stop(self, text: str, p: Mapping[str, int]) -> str | None:
        self.timers.run(p["timer"], p["stop"] != 1, self.now)
        return None

    def _cmd_motion_stop(self, text: str, p: Mapping[str, int]) -> str | None:
        self._stop_all("Motion Stop")
        return None

    def _cmd_set_pr(self, text: str, p: Mapping[str, int]) -> str | None:
        n, kind = p["pr"], p["type"]
        names = ("A1", "A2", "A3", "A4", "A5", "A6") if kind == 1 else "XYZABC"
        values = (*tuple(p[x] for x in names), 0, 0, 0) if kind else (0,) * 9
        if n <= PR_IN_REGISTERS:
            base = R_PR + PR_WORDS * (n - 1)
            self.holding[base] = kind
            for i, v in enumerate(values):
                low, high = split_i32(v)
                self.holding[base + 1 + 2 * i] = u16(low)
                self.holding[base + 2 + 2 * i] = u16(high)
        else:
            self.far_prs[n] = (kind, values)
        return None

    def _cmd_set_frame(self, text: str, p: Mapping[str, int], *, what: str) -> str | None:
        six = tuple(p[x] for x in "XYZABC")
        if what == "tool":
            self.tools[p["tool"]] = six
        else:
            self.bases[p["base"]] = six
        return None

    def _cmd_set_current(self, text: str, p: Mapping[str, int], *, what: str) -> str | None:
        if what == "tool":
            self.current_tool = p["tool"]
        else:
            self.current_base = p["base"]
        return None

    def _cmd_set_home(self, text: str, p: Mapping[str, int]) -> str | None:
        self.home = tuple(p[f"A{i}"] for i in range(1, 7))
        return None

    def _cmd_get(self, text: str, p: Mapping[str, int], *, code: int) -> str | None:
        out: dict[str, int] = {}
        if code == 200:
            kind, values = self.pr(p["pr"])
            names = ("A1", "A2", "A3", "A4", "A5", "A6") if kind == 1 else "XYZABC"
            out = {"pr": p["pr"], "type": kind}
            if kind in (1, 2):
                out.update(zip(names, values[:6], strict=True))
        elif code in (201, 202):
            key = "tool" if code == 201 else "base"
            frames = self.tools if code == 201 else self.bases
            out = {key: p[key], **dict(zip("XYZABC", frames.get(p[key], (0,) * 6), strict=True))}
        elif code == 203:
            out = {"tool": self.current_tool}
        elif code == 204:
            out = {"base": self.current_base}
        elif code == 205:
            out = dict(zip((f"A{i}" for i in range(1, 7)), self.home, strict=True))
        self._put_returns(code, out)
        return None

    def _put_returns(self, code: int, raws: Mapping[str, int]) -> None:
        """Write Get returns into IR202..IR251 through the return layout (Tables 33-43)."""
        form = self.spec.commands[code].returns
        assert form is not None
        self.inputs[IR_RETURNS:IR_RETURNS_END] = [0] * (IR_RETURNS_END - IR_RETURNS)
        fields: list[CommandField] = []
        layout: Layout | None = form.layouts[0]
        if form.select is not None:
            fields.append(form.select)
            sel = raws.get(form.select.name, 0)
            layout = next((lay for lay in form.layouts if lay.when and sel in lay.when), None)
        if layout is not None:
            fields.extend(layout.fields)
        for f in fields:
            raw = raws.get(f.name)
            if raw is None:
                continue
            if f.type in ("i32", "u32"):
                low, high = split_i32(raw)
                self.inputs[f.reg] = u16(low)
                self.inputs[f.reg + 1] = u16(high)
            else:
                self.inputs[f.reg] = u16(raw)

    # ------------------------------------------------------------------ motion

    @property
    def _override(self) -> float:
        """The speed setting (R100) as a fraction."""
        return s16(self.holding[R_SPEED]) / 100

    def _queue(self, m: Motion) -> None:
        if self.motion is None:
            self._begin(m)
        else:
            self.queue.append(m)

    def _begin(self, m: Motion) -> None:
        """Fix the path of ``m`` from where the robot is now, at the speed in force now."""
        self.motion = m
        here = self.joints if m.space == "joint" else self.pose
        start_motion(
            m,
            (*here, *self.ext),
            override=self._override,
            joint_speed=self.joint_speed,
            cart_speed=self.cart_speed,
            rot_speed=self.rot_speed,
        )

    def _place(self, m: Motion) -> None:
        values = position(m)
        if m.space == "joint":
            self.joints[:] = values[:6]
        else:
            self.pose[:] = values[:6]
        self.ext[:] = values[6:9]

    def _finish(self, at: float) -> None:
        m = self.motion
        assert m is not None
        self.motion = None
        self._event("motion", f"done: {m.command}", ok=True, ts=at)
        self._start_next()

    def _start_next(self) -> None:
        if self.queue and self.motion is None:
            self._begin(self.queue.popleft())

    def _jog(self, m: Motion, dt: float) -> None:
        assert m.jog is not None
        axis, direction = m.jog
        d = direction * jog_rate(axis, self._override) * dt
        if axis < 6:
            self.joints[axis] += d
        elif axis < 12:
            self.pose[axis - 6] += d
        else:
            self.ext[axis - 12] += d

    def _stop_all(self, why: str) -> None:
        if self.motion is not None:
            self._event("stop", f"{self.motion.command} stopped ({why})")
        self.motion = None
        self.queue.clear()

    def _set_acc(self, acc: int) -> None:
        self.acc_ms = max(10, min(1000, round(20000 / max(acc, 1))))

    # ------------------------------------------------------------------ signals

    def _write_coils(self, address: int, bits: list[int]) -> None:
        old_hold, old_stop = self.coils[SI_HOLD], self.coils[SI_STOP]
        self.coils[address : address + len(bits)] = bits
        self.held = bool(self.coils[SI_HOLD])
        if self.held != bool(old_hold):
            self._event(
                "stop" if self.held else "motion", "SI2 Hold " + ("on" if self.held else "off")
            )
        if self.coils[SI_STOP] and not old_stop:
            self._stop_all("SI3 Stop")

    def _publish_so(self) -> None:
        self.discrete[SO_RUN] = 1 if self.motion is not None and not self.held else 0
        self.discrete[SO_HELD] = 1 if self.motion is not None and self.held else 0
        self.discrete[SO_FAULT] = 1 if self.fault else 0
        self.discrete[SO_READY] = 0 if self.fault else 1

    def _publish_inputs(self) -> None:
        ir = self.inputs
        m = self.motion
        ir[IR_SPEED] = self.holding[R_SPEED]
        ir[IR_CODE] = u16(m.code) if m is not None else 0
        ir[IR_QUEUE] = min(len(self.queue), 0x7FFF)
        for i, v in enumerate(self.joints):
            self._put32(ir, IR_JOINTS + 2 * i, round(v * 1000))
        for i, v in enumerate(self.pose):
            self._put32(ir, IR_POSE + 2 * i, round(v * 1000))
        self._put32(ir, IR_DRIVE_ERROR, 0)
        ir[IR_HRSS_ERROR], ir[IR_HRSS_ERROR + 1] = self.fault & 0xFFFF, self.fault >> 16
        moving = m is not None and not self.held
        self._put32(ir, IR_TCP_SPEED, round(m.tcp_speed * 1000) if moving and m else 0)
        ir[IR_EXCITED] = 1
        ir[IR_ACC_TIME] = self.acc_ms
        ir[IR_MOTION] = self.motion_state

    @staticmethod
    def _put32(regs: list[int], at: int, value: int) -> None:
        low, high = split_i32(value)
        regs[at], regs[at + 1] = u16(low), u16(high)

    def _event(self, kind: str, text: str, *, ok: bool = True, ts: float | None = None) -> None:
        """Tell ``on_event``; a callback that raises is detached (kept in ``event_error``)."""
        if self.on_event is None:
            return
        try:
            self.on_event(SimEvent(self.now if ts is None else ts, kind, text, ok))
        except Exception as exc:  # a broken console must not break the robot
            self.on_event = None
            self.event_error = exc


_Handler = Callable[[SimRobot, str, Mapping[str, int]], "str | None"]

_HANDLERS: dict[int, _Handler] = {
    0: lambda r, t, p: r._cmd_move(t, p, linear=False),
    1: lambda r, t, p: r._cmd_move(t, p, linear=True),
    2: SimRobot._cmd_circ,
    3: SimRobot._cmd_jog,
    4: SimRobot._cmd_home,
    5: SimRobot._cmd_t_stop,
    6: SimRobot._cmd_motion_stop,
    100: SimRobot._cmd_set_pr,
    101: lambda r, t, p: r._cmd_set_frame(t, p, what="tool"),
    102: lambda r, t, p: r._cmd_set_frame(t, p, what="base"),
    103: lambda r, t, p: r._cmd_set_current(t, p, what="tool"),
    104: lambda r, t, p: r._cmd_set_current(t, p, what="base"),
    105: SimRobot._cmd_set_home,
    200: lambda r, t, p: r._cmd_get(t, p, code=200),
    201: lambda r, t, p: r._cmd_get(t, p, code=201),
    202: lambda r, t, p: r._cmd_get(t, p, code=202),
    203: lambda r, t, p: r._cmd_get(t, p, code=203),
    204: lambda r, t, p: r._cmd_get(t, p, code=204),
    205: lambda r, t, p: r._cmd_get(t, p, code=205),
}
