"""The HRSS data the simulator is driven by, from :mod:`mbmon.semantics` (one import site).

The simulator knows no register address or command layout of its own: the
address map comes from the ``hrss`` register profile (``profiles/hrss.toml``)
and the command layouts, ranges and return layouts from
``profiles/hrss_commands.toml``, the same data the analyzer reads. This module
is the only place in :mod:`mbmon.sim` that imports from :mod:`mbmon.semantics`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from mbmon.semantics.hrss import (
    CommandSpec,
    Decoded,
    Layout,
    Spec,
    decode_command,
    decode_returns,
    load_spec,
)
from mbmon.semantics.hrss import Field as CommandField
from mbmon.semantics.profile import TABLES, Profile, load_profile
from mbmon.semantics.words import join_i32, s16, split_i32, u16

__all__ = [
    "TABLES",
    "CommandField",
    "CommandSpec",
    "Decoded",
    "Layout",
    "Plan",
    "Profile",
    "Spec",
    "address_map",
    "command_spec",
    "decode_command",
    "decode_returns",
    "hrss_profile",
    "join_i32",
    "plan",
    "s16",
    "served_functions",
    "split_i32",
    "u16",
]


@lru_cache(maxsize=1)
def hrss_profile() -> Profile:
    """The built-in ``hrss`` register map."""
    return load_profile("hrss")


def served_functions() -> frozenset[int]:
    """The function codes HRSS serves (the profile's ``functions``, manual Table 10)."""
    codes = hrss_profile().functions
    if codes is None:
        raise ValueError("the hrss profile does not list the function codes it serves")
    return frozenset(codes)


def command_spec() -> Spec:
    """The built-in HRSS command layouts (Tables 16-43)."""
    return load_spec()


@lru_cache(maxsize=1)
def address_map() -> dict[str, tuple[tuple[int, int], ...]]:
    """Per table, the merged ``[start, end)`` address ranges the ``hrss`` profile defines.

    An access that leaves these ranges is answered with exception 02.
    """
    out: dict[str, tuple[tuple[int, int], ...]] = {}
    profile = hrss_profile()
    for table in TABLES:
        spans = sorted((e.address, e.end_address()) for e in profile.entries(table))
        merged: list[tuple[int, int]] = []
        for start, end in spans:
            if merged and start <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(merged[-1][1], end))
            else:
                merged.append((start, end))
        out[table] = tuple(merged)
    return out


@dataclass(frozen=True, slots=True)
class Plan:
    """Every address the simulator uses, read from the ``hrss`` profile and the command spec.

    ``sizes`` is one past the last address per table. Ranges give the address
    of element n = 1 and the stride between elements.
    """

    sizes: Mapping[str, int]
    si: int  # coil of SI1
    do: int  # coil of DO[1]
    so: int  # discrete input of SO1
    di: int  # discrete input of DI[1]
    set_speed: int  # R100
    speed: int  # IR100
    code: int  # IR101
    queue: int  # IR102
    queue_max: int
    execute: int  # R200
    command: int  # R201
    params_end: int  # one past R251
    status: int  # IR200
    action: int  # IR201
    returns: int  # IR202
    returns_end: int  # one past IR251
    joints: int  # IR300 (A1 low word)
    pose: int  # IR400 (X low word)
    drive_error: int
    hrss_error: int
    tcp_speed: int
    excited: int
    acc_time: int
    motion: int  # IR524
    timer: int  # R300: Timer[1] low word
    timer_stride: int
    timers: int  # Timer[1..timers]
    pr: int  # R1000: PR[1].type
    pr_stride: int
    prs: int  # PR[1..prs] in holding registers


def _entry(profile: Profile, table: str, name: str) -> Any:
    for e in profile.entries(table):
        if e.name == name:
            return e
    raise LookupError(f"hrss profile: no {name} in {table}")


@lru_cache(maxsize=1)
def plan() -> Plan:
    """The simulator's addresses (see :class:`Plan`), from the data, once."""
    p, spec = hrss_profile(), command_spec()
    state = {key: f.reg for key, f in spec.state}
    timer = _entry(p, "holding_registers", "Timer[{n}]")
    pr = _entry(p, "holding_registers", "PR[{n}]")
    return Plan(
        sizes={t: spans[-1][1] for t, spans in address_map().items()},
        si=_entry(p, "coils", "SI{n}").address,
        do=_entry(p, "coils", "DO[{n}]").address,
        so=_entry(p, "discrete_inputs", "SO{n}").address,
        di=_entry(p, "discrete_inputs", "DI[{n}]").address,
        set_speed=_entry(p, "holding_registers", "R100").address,
        speed=state["speed_pct"],
        code=_entry(p, "input_registers", "IR101").address,
        queue=spec.reg("queue_reg"),
        queue_max=spec.reg("queue_max"),
        execute=spec.reg("execute_reg"),
        command=spec.reg("command_reg"),
        params_end=spec.reg("param_last") + 1,
        status=spec.reg("status_reg"),
        action=spec.reg("action_reg"),
        returns=spec.reg("return_first"),
        returns_end=spec.reg("return_last") + 1,
        joints=state["a1"],
        pose=state["x"],
        drive_error=state["error_drive"],
        hrss_error=state["error_hrss"],
        tcp_speed=state["tcp_speed"],
        excited=state["excitation"],
        acc_time=state["acc_time"],
        motion=spec.reg("motion_reg"),
        timer=timer.address,
        timer_stride=timer.stride or timer.words,
        timers=timer.n_range[1],
        pr=pr.address,
        pr_stride=pr.stride or pr.words,
        prs=pr.n_range[1],
    )
