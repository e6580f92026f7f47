"""A simulated HRSS robot controller: Modbus server, state machine and client program.

* :class:`~mbmon.sim.robot.SimRobot`: the register map and command protocol as a
  pure state machine (time is an input);
* :class:`~mbmon.sim.server.SimServer`: that robot served over Modbus/TCP or RTU
  by pymodbus (imported only when a server starts);
* :func:`~mbmon.sim.program.run_program`: the manual's §5.4.5.2 client program
  (plus LIN, Set/Get PR, JOG) run step by step against any HRSS-like server.

A test partner and a teaching tool, not a robot simulator: see docs/sim.md.
"""

from __future__ import annotations

from mbmon.sim.program import ProgramError, ProgramResult, Step, run_program
from mbmon.sim.robot import MotionState, SimEvent, SimRobot
from mbmon.sim.server import SimServer

__all__ = [
    "MotionState",
    "ProgramError",
    "ProgramResult",
    "SimEvent",
    "SimRobot",
    "SimServer",
    "Step",
    "run_program",
]
