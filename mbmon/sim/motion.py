"""Robot motion over time for the simulator: a motion's path, its duration, where it is.

No kinematics: a joint target moves A1..A6 and a Cartesian target X..C
(linear interpolation at the commanded speed; CIRC along the circular arc
through its auxiliary point). Pure functions of the numbers given: the
:class:`~mbmon.sim.robot.SimRobot` keeps the state and the clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

__all__ = ["Motion", "MotionState", "arc", "jog_rate", "position", "start_motion"]

NOMINAL_REACH_MM = 500.0  # IR520 for joint motions: fastest joint's angular speed x this
MIN_MOTION_S = 0.1  # even a move to where the robot already is reports Running for this long


class MotionState:
    """IR524 values (Table 14)."""

    IDLE = 1
    RUNNING = 2
    HOLD = 3
    DELAY = 4


@dataclass(slots=True)
class Motion:
    """One motion: a target picked at execute time, a path fixed when it starts."""

    command: str  # text of the command, for events
    space: str  # "joint" | "cart"
    target: tuple[float, ...]  # 6 values (deg, or mm/deg) + 3 external axes
    speed: float  # PTP: fraction of the maximum (0..2); LIN/CIRC: mm/s
    linear: bool  # LIN/CIRC: speed in mm/s
    code: int = 0  # custom command code (R226 / R237) -> IR101
    aux: tuple[float, ...] | None = None  # CIRC auxiliary point (X..C)
    hold_to_run: bool = False  # GO HOME: stops when R200 returns to 0
    jog: tuple[int, int] | None = None  # JOG: (axis 0..14, direction -1/1)
    # set when the motion starts
    start: tuple[float, ...] = ()
    duration: float = 0.0
    elapsed: float = 0.0
    tcp_speed: float = 0.0  # mm/s reported in IR520 while it runs
    path: Callable[[float], tuple[float, ...]] | None = None


def start_motion(
    m: Motion,
    start: Sequence[float],
    *,
    override: float,
    joint_speed: float,
    cart_speed: float,
    rot_speed: float,
) -> None:
    """Fix the path of ``m`` from ``start`` (A1..A6 or X..C, then E1..E3) at the speeds
    in force (``override``: the speed setting as a fraction; joint speeds in deg/s,
    Cartesian in mm/s, rotation in deg/s): its duration and reported TCP speed."""
    m.elapsed = 0.0
    m.start = tuple(start)
    delta = [t - s for s, t in zip(m.start, m.target, strict=True)]
    if m.space == "joint":
        rate = min(m.speed, joint_speed) if m.linear else joint_speed * m.speed
        rate *= override
        m.duration = max(abs(d) for d in delta) / rate
        m.tcp_speed = rate * math.pi / 180 * NOMINAL_REACH_MM
        m.path = None
    else:
        lin = (m.speed if m.linear else cart_speed * m.speed) * override
        rot = rot_speed * (1.0 if m.linear else m.speed) * override
        length = math.dist(m.start[:3], m.target[:3])
        if m.aux is not None:
            m.path, length = arc(m.start[:3], m.aux[:3], m.target[:3])
        m.duration = max(length / lin, max(abs(d) for d in delta[3:]) / rot)
        m.tcp_speed = lin if length > 0 else 0.0
    if m.duration < MIN_MOTION_S:
        m.duration = MIN_MOTION_S
        if m.space == "cart":
            m.tcp_speed = 0.0 if math.dist(m.start[:3], m.target[:3]) == 0 else m.tcp_speed


def position(m: Motion) -> list[float]:
    """Where ``m`` has brought the robot after ``m.elapsed`` seconds (its 9 values)."""
    f = m.elapsed / m.duration if m.duration > 0 else 1.0
    values = [s + (t - s) * f for s, t in zip(m.start, m.target, strict=True)]
    if m.path is not None:
        values[:3] = m.path(f)
    return values


def jog_rate(axis: int, override: float) -> float:
    """How fast JOG moves ``axis`` (0..14) at the speed setting ``override`` (fraction)."""
    if axis < 6:
        return 10.0 * override  # deg/s
    if axis < 9:
        return 50.0 * override  # mm/s
    return 10.0 * override  # deg/s (A, B, C) or units/s (E1..E3)


def arc(
    p0: Sequence[float], p1: Sequence[float], p2: Sequence[float]
) -> tuple[Callable[[float], tuple[float, ...]], float]:
    """The circular arc from ``p0`` through ``p1`` to ``p2`` as (f in 0..1 -> point, length).

    Collinear or coincident points give the polyline p0 -> p1 -> p2 instead.
    """

    def sub(a: Sequence[float], b: Sequence[float]) -> tuple[float, ...]:
        return tuple(x - y for x, y in zip(a, b, strict=True))

    def cross(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
        return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])

    def dot(a: Sequence[float], b: Sequence[float]) -> float:
        return sum(x * y for x, y in zip(a, b, strict=True))

    a, b = sub(p1, p0), sub(p2, p0)
    n = cross(a, b)
    nn = dot(n, n)
    if nn < 1e-12:
        l1, l2 = math.dist(p0, p1), math.dist(p1, p2)
        total = l1 + l2

        def poly(f: float) -> tuple[float, ...]:
            s = f * total
            if total == 0:
                return tuple(p2)
            if s <= l1 and l1 > 0:
                return tuple(x + (y - x) * s / l1 for x, y in zip(p0, p1, strict=True))
            g = (s - l1) / l2 if l2 > 0 else 1.0
            return tuple(x + (y - x) * g for x, y in zip(p1, p2, strict=True))

        return poly, total
    aa, bb = dot(a, a), dot(b, b)
    t1, t2 = cross(b, n), cross(n, a)
    center = tuple(p0[i] + (aa * t1[i] + bb * t2[i]) / (2 * nn) for i in range(3))
    r = math.dist(center, p0)
    u = tuple(x / r for x in sub(p0, center))
    nh = tuple(x / math.sqrt(nn) for x in n)
    v = cross(nh, u)

    def angle(p: Sequence[float]) -> float:
        d = sub(p, center)
        return math.atan2(dot(d, v), dot(d, u)) % (2 * math.pi)

    th1, th2 = angle(p1), angle(p2)
    sweep = th2 if th1 < th2 else th2 - 2 * math.pi

    def arc(f: float) -> tuple[float, ...]:
        th = sweep * f
        c, s = math.cos(th), math.sin(th)
        return tuple(center[i] + r * (c * u[i] + s * v[i]) for i in range(3))

    return arc, abs(sweep) * r
