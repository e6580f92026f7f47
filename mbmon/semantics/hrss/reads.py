"""What one FC 04 answer carries for the HRSS session: where the watched input
registers sit in it (:class:`ReadPlan`, made once per read shape) and the robot
state its words give (:func:`read_state`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from mbmon.semantics.hrss.spec import Spec

__all__ = ["ReadPlan", "StateField", "read_plan", "read_state"]

_S16, _U16, _I32, _U32 = range(4)
_WORD_TYPES = {"s16": _S16, "u16": _U16, "i32": _I32, "u32": _U32}
#: (state key, offset of the first word, offset of the last word, word type, scale mode, factor);
#: scale mode 0: the raw number, 1: raw / factor (a power of ten), 2: raw * factor
StateField = tuple[str, int, int, int, int, float]


@dataclass(frozen=True, slots=True, eq=False)  # each plan is its own: a cheap dict key
class ReadPlan:
    """Offsets, in one FC 04 read, of the input registers the session watches (None: absent)."""

    addresses: range  # the registers the read carries
    status: int | None
    action: int | None
    returns: tuple[int, ...]  # addresses of IR202..IR251 in the read
    queue: int | None
    motion: int | None
    state: tuple[StateField, ...]


def read_plan(spec: Spec, returns: range, address: int, count: int) -> ReadPlan:
    """Where the registers the session watches sit in a read of ``count`` from ``address``
    (``returns``: the Get commands' return registers)."""
    end = address + count

    def offset(reg: int) -> int | None:
        return reg - address if address <= reg < end else None

    p = spec
    state: list[StateField] = []
    for key, f in p.state:
        regs = f.regs
        if regs[0] < address or regs[-1] >= end:
            continue  # both words from this very answer, or nothing
        mode, k = (0, 1.0)
        if f.scale != 1:
            d = f.decimals
            mode, k = (1, 10**d) if d and abs(f.scale - 10.0**-d) < 1e-12 else (2, f.scale)
        state.append((key, regs[0] - address, regs[-1] - address, _WORD_TYPES[f.type], mode, k))
    return ReadPlan(
        addresses=range(address, end),
        status=offset(p.reg("status_reg")),
        action=offset(p.reg("action_reg")),
        returns=tuple(r for r in range(address, end) if r in returns),
        queue=offset(p.reg("queue_reg")),
        motion=offset(p.reg("motion_reg")),
        state=tuple(state),
    )


def read_state(
    fields: tuple[StateField, ...], values: Sequence[int], state: dict[str, float]
) -> bool:
    """Put the state values whose words are all in this answer into ``state`` (read
    as ``Field.raw``/``value`` do); whether one changed."""
    changed = False
    for key, lo, hi, wtype, mode, k in fields:
        if wtype == _S16:
            raw = values[lo] & 0xFFFF
            if raw & 0x8000:
                raw -= 0x10000
        elif wtype == _U16:
            raw = values[lo] & 0xFFFF
        elif wtype == _I32:
            high = values[hi] & 0xFFFF
            raw = (high - 0x10000 if high & 0x8000 else high) * 65536 + (values[lo] & 0xFFFF)
        else:
            raw = ((values[hi] & 0xFFFF) << 16) | (values[lo] & 0xFFFF)
        val = float(raw) if mode == 0 else raw / k if mode == 1 else float(raw * k)
        if state.get(key) != val:
            state[key] = val
            changed = True
    return changed
