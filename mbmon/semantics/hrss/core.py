"""What the compiled core asks of an HRSS session (``core_ready``, ``core_watch``,
``core_answer``, ``core_write_answer``; the contract is
:class:`~mbmon.semantics.session.Session`'s): the answers whose words would change what
the session says, and the session's notes and steps for the answers the core notes
itself. A mixin of :class:`~mbmon.semantics.hrss.session.HrssSession`, which owns the
state it reads."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from mbmon.model import CommandUpdate, Stream
from mbmon.semantics.hrss.codes import HOLDING_READS, INPUT_READS, MOVING
from mbmon.semantics.hrss.steps import Exec, StepOut, Write
from mbmon.semantics.session import CoreWatch

if TYPE_CHECKING:
    from mbmon.semantics.hrss.spec import Spec


class HrssCoreSupport:
    """The core-facing half of the HRSS session (see the module's docstring)."""

    if TYPE_CHECKING:  # the session's state this half reads
        _spec: Spec
        _active: Exec | None
        _queue_over: bool
        _motion: int | None
        _holding: dict[int, int]
        _exec_reg: int
        _returns: range
        _writes: dict[tuple[Any, ...], Write]

        def next_deadline(self) -> float | None: ...
        def _begin(self, ts: float, stream: Stream, notes: list[str]) -> StepOut: ...
        def _late(self, ts: float, out: StepOut) -> None: ...
        def _confirm(self, key: tuple[Any, ...]) -> None: ...
        def _answer_values(
            self, fc: int, address: int, values: Sequence[int], ts: float, out: StepOut
        ) -> None: ...

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # CoreWatch by what it was made from (see core_watch)
        self._watches: dict[tuple[Any, ...], tuple[Exec | None, CoreWatch]] = {}

    core_ready = True

    def core_watch(self) -> CoreWatch:
        """The answers whose words would change what this session says (see
        :class:`~mbmon.semantics.session.CoreWatch`): every holding-register read
        (the image commands are decoded from), the Get commands' returns, the command
        status while a command waits for one, the queue length crossing its limit, the
        motion state when it changes or while the command in flight is moving; and
        the time from which a step may report a command that never completed.

        Made again only when what it depends on changed (it is asked after every call
        the core makes, most of which change none of it)."""
        a = self._active
        key = (
            None if a is None else (id(a), a.done, a.looked, a.moving, a.settled, a.warned, a.t0),
            self._queue_over,
            self._motion,
            self._holding.get(self._exec_reg),
        )
        known = self._watches.get(key)
        if known is not None and known[0] is a:  # (the same command, not one at its address)
            return known[1]
        if len(self._watches) >= 16:  # a few states recur (the motion toggling): bounded
            self._watches.clear()
        watch = self._core_watch()
        self._watches[key] = (a, watch)
        return watch

    def _core_watch(self) -> CoreWatch:
        p = self._spec
        always: list[tuple[int, int, int, int, int]] = [
            (fc, 0, 0xFFFF, 1, 0) for fc in sorted(HOLDING_READS)
        ]
        status, queue, motion = p.reg("status_reg"), p.reg("queue_reg"), p.reg("motion_reg")
        limit = int(p.protocol["queue_max"])
        a = self._active
        for fc in sorted(INPUT_READS):
            always.append((fc, self._returns.start, self._returns.stop - 1, 1, 0))
            if a is not None and not a.done:
                always.append((fc, status, status, 1, 0))
            if self._queue_over:
                always.append((fc, queue, queue, limit + 1, 0x7FFF))
            else:
                always.append((fc, queue, queue, -0x8000, limit))
            m = self._motion
            if m is not None and self._motion_unchanged(m):
                always.append((fc, motion, motion, m, m))
            else:
                always.append((fc, motion, motion, 1, 0))
        deadline = self.next_deadline()
        return CoreWatch(math.inf if deadline is None else deadline, tuple(always))

    def _motion_unchanged(self, m: int) -> bool:
        """Whether reading the motion state ``m`` again would change nothing (see
        :meth:`_motion_read`)."""
        a = self._active
        if a is None or a.spec is None or not a.spec.motion:
            return True
        if not a.looked:
            return False
        if m in MOVING:
            return a.moving
        return not (m == 1 and a.moving and not a.settled)

    def core_answer(
        self, fc: int, address: int, values: tuple[int, ...], ts: float, stream: Stream
    ) -> tuple[list[str], list[CommandUpdate]]:
        """:meth:`follow` of an answered read, for the compiled core: the session's
        notes and command steps (the state it keeps is not asked for)."""
        out = self._begin(ts, stream, [])
        self._answer_values(fc, address, values, ts, out)
        self._late(ts, out)
        return out.notes, out.commands or []

    def core_write_answer(
        self, request: tuple[float, int, int, bytes], ts: float, stream: Stream
    ) -> tuple[list[str], list[CommandUpdate]] | None:
        """:meth:`follow` of a register write's answer, for the compiled core: the
        write is confirmed (its request was followed: ``None`` when it was not, and the
        core hands the step to the annotator); a write's answer reads nothing."""
        if request not in self._writes:
            return None
        out = self._begin(ts, stream, [])
        self._confirm(request)
        self._late(ts, out)
        return out.notes, out.commands or []
