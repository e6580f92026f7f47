"""HRSS command session: the R200/R201..R251 handshake as a lifecycle of commands.

A client drives an HRSS controller by writing a command number to R201 and its
parameters to R202..R251 (FC 06/10/17, in any number of requests), then R200 = 1
to execute; the controller answers in IR200 (1 success, 2 fail), IR201 (current
action) and, for the Get commands, IR202..IR251; the client resets R200 = 0
before the next command (manual §5.3.3.5, Tables 14-43).

:class:`HrssSession` follows that handshake for one server endpoint and unit,
from pairing steps (:class:`~mbmon.model.Transaction`). It keeps the register
image seen so far, turns it into :class:`~mbmon.model.CommandUpdate` steps with
the command in HRSS program form, decodes Get returns, warns about protocol
misuse and keeps the robot state (joint angles, pose, speeds, errors, motion).

Every command layout, enum, range and state register comes from
``profiles/hrss_commands.toml``; this module is the code that reads it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any

from mbmon.model import (
    Annotation,
    CommandUpdate,
    Frame,
    Kind,
    Phase,
    Stream,
    Transaction,
    TxStatus,
)
from mbmon.protocol.functions import SHAPE, mask_write
from mbmon.semantics.hrss.codes import HOLDING_READS, INPUT_READS, MOVING, WRITE_FCS
from mbmon.semantics.hrss.core import HrssCoreSupport
from mbmon.semantics.hrss.reads import ReadPlan, read_plan, read_state
from mbmon.semantics.hrss.render import (
    Decoded,
    decode_command_from,
    decode_returns,
    parameter_rows,
)
from mbmon.semantics.hrss.spec import load_spec
from mbmon.semantics.hrss.steps import Exec, LiveImage, StepOut, Write, pop_oldest, write_key
from mbmon.semantics.session import Panel, Session, annotation
from mbmon.semantics.words import s16

#: a decoded command with the registers its decode read and the words they held
_Remembered = tuple[tuple[int, ...], tuple[int | None, ...], Decoded]
_DECODED_MAX = 128  # decoded commands a session remembers (see HrssSession._decode)
_DECODED_PER_CODE = 8  # of them with the same R201 word (the newest)
_ANSWERS_MAX = 64  # FC 04 answers (of different shapes) kept before they go to the image

_PENDING, _ANSWERED = TxStatus.PENDING, TxStatus.ANSWERED


class HrssSession(HrssCoreSupport, Session):
    """Per (server endpoint, unit): the register image seen so far and the command protocol.

    The device session (:class:`~mbmon.semantics.session.Session`) the ``hrss``
    profile names (``session = "hrss"``).

    Writes (FC 06, 10, 0x16, 17) update the holding image when the *request* is
    seen, so that a command executes on the frame that carries R200 = 1; the
    written registers stay unconfirmed until the answer, and an exception
    answer puts the old values back. Reads (FC 03, 04, 17) update the images
    from the answer. ``complete_timeout`` (seconds of capture time, default from
    the TOML) bounds how long a command may go without completing while the
    client is watching IR200/IR524; :meth:`tick` and :meth:`next_deadline` let
    that fire on time while the line is silent. At most ``max_writes``
    unanswered writes are remembered (the oldest is dropped with a note).
    """

    def __init__(
        self,
        stream: Stream,
        unit: int,
        *,
        complete_timeout: float | None = None,
        max_writes: int = 256,
    ) -> None:
        super().__init__(stream, unit)
        self._spec = load_spec()
        p = self._spec
        self._exec_reg = p.reg("execute_reg")
        self._cmd_reg = p.reg("command_reg")
        self._params = range(p.reg("param_first"), p.reg("param_last") + 1)
        self._returns = range(p.reg("return_first"), p.reg("return_last") + 1)
        self._timeout = float(
            complete_timeout if complete_timeout is not None else p.protocol["complete_timeout"]
        )
        self._holding: dict[int, int] = {}
        self._inputs: dict[int, int] = {}  # read it through _input_image()
        self._answers: dict[ReadPlan, Sequence[int]] = {}  # not yet in _inputs, oldest first
        self._unconfirmed: set[int] = set()
        self._writes: dict[tuple[Any, ...], Write] = {}  # unanswered, oldest first, bounded
        self._max_writes = max_writes
        self._block: set[int] = set()  # R201..R251 written since the last execute
        self._block_code: int | None = None  # command whose WRITTEN was emitted for the block
        self._active: Exec | None = None  # last executed command
        self._get: Exec | None = None  # last executed command that has returns
        self._motion: int | None = None
        self._queue_over = False
        self._state: dict[str, float] = {}
        self._plans: dict[tuple[int, int], ReadPlan] = {}  # (address, count) of FC 04 reads
        # what the step being followed produces (see follow)
        self._out = StepOut(unit, stream, self._state)
        # decoded commands by the R201 word, each with the registers the decode read and
        # their words: the same words decode the same (see _decode); bounded
        self._decoded: dict[int | None, list[_Remembered]] = {}
        self._decoded_count = 0

    # ------------------------------------------------------------------ public views

    @property
    def state(self) -> dict[str, float]:
        """Current robot state (a copy): keys and units in docs/commands.md."""
        return dict(self._state)

    @property
    def holding(self) -> Mapping[int, int]:
        """Holding register image (address -> unsigned word), writes applied on request."""
        return MappingProxyType(self._holding)

    @property
    def inputs(self) -> Mapping[int, int]:
        """Input register image (address -> unsigned word) from FC 04 answers (a live view)."""
        return LiveImage(self._input_image)

    @property
    def unconfirmed(self) -> frozenset[int]:
        """Holding registers written by a request whose answer has not been seen."""
        return frozenset(self._unconfirmed)

    def panel(self) -> Panel:
        """The written command registers (R200..R251), named as the command in R201 says
        (:func:`~mbmon.semantics.hrss.render.parameter_rows`), for the live monitor."""
        p = self._spec
        first = min(p.reg("execute_reg"), p.reg("command_reg"))
        title = f"command registers R{first}..R{p.reg('param_last')} as written"
        return Panel(title, tuple(parameter_rows(self._holding, self.unconfirmed, p)))

    # ------------------------------------------------------------------ feed

    def feed(self, tx: Transaction) -> Annotation:
        """Follow one pairing step: the notes, command steps and state change it causes."""
        return self.follow(tx, [])

    def follow(self, tx: Transaction, notes: list[str]) -> Annotation:
        """:meth:`feed`, with the profile's ``notes`` on the same frame first.

        The step's one annotation: ``notes`` (which the session's own notes are
        added to), the command steps and the state when it changed; the shared
        empty annotation when there is none of these.
        """
        req = tx.request
        frame = req if req is not None else tx.response
        if frame is None or frame.unit != self.unit:
            return annotation(notes)
        status = tx.status
        if status is _PENDING and req is not None and req.pdu.fc not in WRITE_FCS:
            # a read asked for: it changes no image, only the clock can say something
            if not self.may_time_out_by(tx.ts):
                return annotation(notes)
        ts = tx.ts
        out = self._begin(ts, frame.stream, notes)
        if status is _ANSWERED and req is not None and tx.response is not None:
            if req.pdu.fc in WRITE_FCS:
                key = write_key(req)
                if key not in self._writes:
                    self._request(req, out)  # the request was never fed on its own
                self._confirm(key)
            self._answer(req, tx.response, out)
        elif status is _PENDING and req is not None:
            if req.pdu.fc in WRITE_FCS:  # reads change no image on request
                self._request(req, out)
        elif tx.status is TxStatus.EXCEPTION and req is not None:
            self._rejected(req, tx.response, out)  # a write never fed as PENDING: nothing to undo
        elif tx.status is TxStatus.TIMEOUT and req is not None:
            self._writes.pop(write_key(req), None)  # values stay, still unconfirmed
        self._late(ts, out)
        return out.annotation()

    def _begin(self, ts: float, stream: Stream, notes: list[str]) -> StepOut:
        """The step's output, emptied, for a step at ``ts`` on ``stream`` (``notes`` first)."""
        out = self._out
        out.ts = ts
        out.stream = stream
        out.notes = notes
        out.commands = None
        out.state_changed = False
        return out

    def _late(self, ts: float, out: StepOut) -> None:
        """Every step's last look: the command in flight times out by ``ts``."""
        a = self._active
        if a is not None and ts - a.t0 > self._timeout:
            self._check_timeout(ts, out)

    def wants_read_request(self, ts: float) -> bool:
        """A read asked for changes no image: :meth:`follow` needs it only when
        :meth:`may_time_out_by` ``ts``."""
        return self.may_time_out_by(ts)

    def may_time_out_by(self, ts: float) -> bool:
        """Whether a step at ``ts`` that changes nothing (a read asked for) can say something.

        Only the clock can then: the command in flight may have gone
        ``complete_timeout`` without completing.
        """
        a = self._active
        return a is not None and ts - a.t0 > self._timeout and self._may_time_out(a)

    def tick(self, now: float) -> list[CommandUpdate]:
        """Time ``now`` (capture time) passed with no transaction: the command steps it makes due.

        A command that has gone ``complete_timeout`` without completing while the
        client watched IR200/IR524 is reported "never completed" here, on time,
        even while the line is silent; a later transaction does not repeat it.
        """
        a = self._active
        if a is None:
            return []
        out = StepOut(self.unit, a.stream, self._state)
        out.ts = now
        self._check_timeout(now, out)
        return out.commands or []

    def next_deadline(self) -> float | None:
        """The earliest time at which :meth:`tick` reports something, or ``None``.

        ``None`` while nothing can time out (no command in flight, the client
        never looked at its status, a hold-to-run command still held, the robot
        still moving): the next transaction changes that, not the clock.
        """
        a = self._active
        if a is None or not self._may_time_out(a):
            return None
        deadline = a.t0 + self._timeout
        while deadline - a.t0 <= self._timeout:  # the first time _check_timeout fires
            deadline = math.nextafter(deadline, math.inf)
        return deadline

    # ------------------------------------------------------------------ writes

    def _request(self, req: Frame, out: StepOut) -> None:
        pdu = req.pdu
        if pdu.kind is not Kind.REQUEST:
            return
        writes: list[tuple[int, int | None]] = []
        shape = SHAPE.get(pdu.fc) if pdu.fc in WRITE_FCS else None
        if shape == "write_single" and pdu.address is not None and pdu.values:
            writes = [(pdu.address, pdu.values[0])]
        elif shape == "write_multiple" and pdu.address is not None and pdu.values is not None:
            writes = [(pdu.address + i, v) for i, v in enumerate(pdu.values)]
        elif shape == "read_write":
            addr = pdu.fields.get("write_address")
            vals = pdu.fields.get("write_values")
            if addr is not None and vals is not None:
                writes = [(addr + i, v) for i, v in enumerate(vals)]
        elif shape == "mask_write" and pdu.address is not None:
            old = self._holding.get(pdu.address)
            and_m, or_m = pdu.fields.get("and_mask"), pdu.fields.get("or_mask")
            if old is None or and_m is None or or_m is None:
                writes = [(pdu.address, None)]  # result unknown
            else:
                writes = [(pdu.address, mask_write(old, and_m, or_m))]
        if not writes:
            return
        w = Write(old={a: self._holding.get(a) for a, _ in writes}, new={})
        for a, v in writes:
            if v is None:
                self._holding.pop(a, None)
            else:
                self._holding[a] = v
                w.new[a] = v
            self._unconfirmed.add(a)
        writes_map = self._writes
        writes_map[write_key(req)] = w
        if len(writes_map) > self._max_writes:
            _, dropped = pop_oldest(writes_map)
            lo, hi = min(dropped.old), max(dropped.old)
            span = f"R{lo}" if lo == hi else f"R{lo}..R{hi}"
            out.note(
                f"warning: more than {self._max_writes} writes unanswered: "
                f"the oldest ({span}) is forgotten, its values stay unconfirmed"
            )
        self._commands(w, req.ts, out)

    def _commands(self, w: Write, ts: float, out: StepOut) -> None:
        params = {a for a in w.new if a == self._cmd_reg or a in self._params}
        execute = w.new.get(self._exec_reg)
        before = w.old.get(self._exec_reg)
        if params:
            new_code = w.new.get(self._cmd_reg)
            if (
                self._block_code is not None
                and new_code is not None
                and (s16(new_code) != self._block_code)
            ):
                self._block.clear()  # a different command is being written
                self._block_code = None
            self._block |= params
        if execute == 1:
            self._execute(w, before, ts, out)
        elif params and self._block_code is None:
            dec = self._decode()
            covered = dec.regs <= self._block
            if dec.code is not None and dec.layout is not None and covered and not dec.missing:
                self._block_code = dec.code
                out.command(
                    Phase.WRITTEN,
                    dec.text,
                    dec.code,
                    params=dec.params,
                    note=f"written: {dec.text}",
                )
        if execute == 0 and before == 1:
            a = self._active
            if a is not None and a.spec is not None and a.spec.hold_to_run and not a.settled:
                a.settled = True
                out.note(f"stop: {a.decoded.text} (R200 = 0 after {ts - a.t0:.3f} s)")
        elif execute is not None and execute not in (0, 1):
            out.warn(
                f"R200 = {s16(execute)} outside 0..1: not an execute or a reset",
                kind="range",
                code=None,
            )

    def _execute(self, w: Write, before: int | None, ts: float, out: StepOut) -> None:
        dec = self._decode()
        old = self._active
        if old is not None and not old.done and not old.settled and old.looked and not old.warned:
            old.warned = True
            out.warn(
                f"never completed: {old.decoded.text} (no IR200 status before the next "
                f"execute, {ts - old.t0:.3f} s)",
                kind="never_completed",
                code=old.decoded.code,
            )
        cmd = self._spec.commands.get(dec.code) if dec.code is not None else None
        ex = Exec(decoded=dec, spec=cmd, t0=ts, stream=out.stream)
        self._active = ex
        w.execute = ex
        if cmd is not None and cmd.returns is not None:
            self._get = ex
        self._block.clear()
        self._block_code = None
        if before == 1:
            out.warn(
                f"execute without reset: R200 was still 1 when {dec.text} was executed "
                "(reset R200 = 0 first, §5.3.3.5)",
                kind="no_reset",
                code=dec.code,
            )
        out.command(
            Phase.EXECUTING, dec.text, dec.code, params=dec.params, note=f"execute: {dec.text}"
        )
        if dec.problems:
            out.warn(
                f"out of range in {dec.text}: " + "; ".join(dec.problems),
                kind="range",
                code=dec.code,
            )

    def _decode(self) -> Decoded:
        """The command the holding image describes (:func:`decode_command`), remembered.

        A decode depends only on the words it reads, so a result is reused when
        every register it read holds the same word (or is still unseen) as then:
        a command is decoded when its block is written and again when it is
        executed, and a cell repeats the same few commands. At most
        :data:`_DECODED_MAX` results are kept (a few kB each), :data:`_DECODED_PER_CODE`
        of them per command number.
        """
        get = self._holding.get
        code_word = get(self._cmd_reg)
        remembered = self._decoded.get(code_word)
        if remembered is not None:
            for regs, words, decoded in remembered:
                if tuple(map(get, regs)) == words:
                    return decoded
        seen: dict[int, int | None] = {}

        def read(reg: int) -> int | None:
            word = seen[reg] = get(reg)
            return word

        decoded = decode_command_from(read, self._spec)
        if self._decoded_count >= _DECODED_MAX:
            self._decoded.clear()
            self._decoded_count = 0
        entries = self._decoded.setdefault(code_word, [])
        if len(entries) >= _DECODED_PER_CODE:  # a short scan on every decode of this code
            del entries[0]
        else:
            self._decoded_count += 1
        entries.append((tuple(seen), tuple(seen.values()), decoded))
        return decoded

    def _confirm(self, key: tuple[Any, ...]) -> None:
        w = self._writes.pop(key, None)
        if w is None:
            return
        for a, v in w.new.items():
            if self._holding.get(a) == v:
                self._unconfirmed.discard(a)

    def _rejected(self, req: Frame, resp: Frame | None, out: StepOut) -> None:
        w = self._writes.pop(write_key(req), None)
        if w is None:
            return
        exc = resp.pdu.exception_code if resp is not None else None
        for a, old in w.old.items():
            if a in w.new and self._holding.get(a) != w.new[a]:
                continue  # written again since: keep the newer value
            if old is None:
                self._holding.pop(a, None)
            else:
                self._holding[a] = old
            self._unconfirmed.discard(a)
        lo, hi = min(w.old), max(w.old)
        span = f"R{lo}" if lo == hi else f"R{lo}..R{hi}"
        out.note(f"write rejected (exception {exc}): {span} unchanged")
        ex = w.execute
        if ex is not None and not ex.done:
            ex.done = True
            out.warn(
                f"execute rejected (exception {exc}): {ex.decoded.text}",
                kind="rejected",
                code=ex.decoded.code,
            )

    # ------------------------------------------------------------------ reads

    def _answer(self, req: Frame, resp: Frame, out: StepOut) -> None:
        rq, rs = req.pdu, resp.pdu
        if rs.kind is not Kind.RESPONSE or rs.values is None or rq.address is None:
            return
        values = rs.values
        if rq.count is not None:
            values = values[: rq.count]
        self._answer_values(rq.fc, rq.address, values, resp.ts, out)

    def _answer_values(
        self, fc: int, address: int, values: Sequence[int], ts: float, out: StepOut
    ) -> None:
        """An answered request of function code ``fc`` at ``address`` read ``values``
        (as many as asked): the images, then what the watched registers say."""
        if fc in HOLDING_READS:
            for i, v in enumerate(values):
                self._holding[address + i] = v
                self._unconfirmed.discard(address + i)
        elif fc in INPUT_READS:
            n = len(values)
            plan = self._plans.get((address, n))
            if plan is None:
                plan = self._read_plan(address, n)
            answers = self._answers  # applied to the input image when it is read
            if plan in answers:
                del answers[plan]  # the newest answer of each shape goes last
            answers[plan] = values
            if len(answers) > _ANSWERS_MAX:
                self._input_image()
            self._inputs_read(plan, values, ts, out)

    def _input_image(self) -> dict[int, int]:
        """The input register image, with the answers not yet applied applied (oldest first).

        FC 04 answers are kept per read shape, newest last, until the image is
        read: a register ends up with the word of the newest answer that
        carried it, as if every answer had been applied in turn.
        """
        answers = self._answers
        if answers:
            image = self._inputs
            for plan, values in answers.items():
                image.update(zip(plan.addresses, values, strict=True))
            answers.clear()
        return self._inputs

    def _read_plan(self, address: int, count: int) -> ReadPlan:
        """:func:`~.reads.read_plan` of a read, remembered by its shape (bounded)."""
        plan = read_plan(self._spec, self._returns, address, count)
        if len(self._plans) >= 4096:  # bounded: a scan of every address cannot grow it
            self._plans.clear()
        self._plans[(address, count)] = plan
        return plan

    def _inputs_read(self, plan: ReadPlan, values: Sequence[int], ts: float, out: StepOut) -> None:
        p = self._spec
        if plan.status is not None:
            a = self._active
            if a is not None and not a.done:  # else _status has nothing to do
                action = None if plan.action is None else s16(values[plan.action])
                self._status(s16(values[plan.status]), action, ts, out)
        if plan.returns:
            self._returns_read(plan.returns, ts, out)
        if plan.queue is not None:
            q = s16(values[plan.queue])
            limit = int(p.protocol["queue_max"])
            if q > limit and not self._queue_over:
                out.warn(
                    f"{q} commands queued (IR102 > {limit}): motion commands will fail",
                    kind="queue",
                    code=None,
                )
            self._queue_over = q > limit
        if plan.motion is not None:
            self._motion_read(s16(values[plan.motion]), ts, out)
        if plan.state:
            out.state_changed |= read_state(plan.state, values, self._state)

    def _status(self, v: int, action: int | None, ts: float, out: StepOut) -> None:
        a = self._active
        if a is None or a.done or ts < a.t0:
            return
        a.looked = True
        if v not in (1, 2):
            return
        a.done, a.status = True, v
        phase = Phase.SUCCESS if v == 1 else Phase.FAIL
        params = dict(a.decoded.params)
        params["status"] = v
        if action is not None:
            params["action"] = action
        dur = ts - a.t0
        word = "success" if v == 1 else "fail"
        out.command(
            phase,
            a.decoded.text,
            a.decoded.code,
            params=params,
            duration=dur,
            note=f"{word}: {a.decoded.text} ({dur:.3f} s)",
        )

    def _returns_read(self, returned: tuple[int, ...], ts: float, out: StepOut) -> None:
        g = self._get
        if g is None or ts < g.t0 or g.status == 2 or g.decoded.code is None:
            return
        g.return_seen.update(returned)
        seen = {r: v for r, v in self._input_image().items() if r in g.return_seen}
        dec = decode_returns(g.decoded.code, seen, self._spec)
        if dec is None or dec.layout is None or dec.missing:
            return
        values = tuple(sorted((k, v) for k, v in dec.params.items()))
        if values == g.returned:
            return
        g.returned = values
        out.command(
            Phase.RETURNED, dec.text, dec.code, params=dec.params, note=f"returned: {dec.text}"
        )
        spec = g.spec
        key = spec.returns.match if spec is not None and spec.returns is not None else None
        if key is not None:
            asked, got_back = g.decoded.params.get(key), dec.params.get(key)
            if asked is not None and got_back is not None and asked != got_back:
                out.warn(
                    f"{g.decoded.text} returned {dec.text.split(' = ')[0]}: stale returns?",
                    kind="stale_returns",
                    code=dec.code,
                )
        if dec.problems:
            out.note("returns out of range: " + "; ".join(dec.problems))

    def _motion_read(self, v: int, ts: float, out: StepOut) -> None:
        prev = self._motion
        self._motion = v
        if v != prev:
            lab = self._spec.label("motion_state", v)
            out.note(
                f"motion: {lab}"
                if prev is None
                else f"motion: {self._spec.label('motion_state', prev)} -> {lab}"
            )
        a = self._active
        if a is None or ts < a.t0 or a.spec is None or not a.spec.motion:
            return
        a.looked = True
        if v in MOVING:
            a.moving = True
        elif v == 1 and a.moving and not a.settled:
            a.settled = True
            out.note(f"motion done: {a.decoded.text} ({ts - a.t0:.3f} s after R200 = 1)")

    # ------------------------------------------------------------------ completion

    def _may_time_out(self, a: Exec) -> bool:
        """Whether the clock alone can make ``a`` "never completed" (its deadline aside)."""
        if a.done or a.settled or a.warned or not a.looked:
            return False
        if a.spec is not None and a.spec.hold_to_run and self._holding.get(self._exec_reg) == 1:
            return False  # JOG / GO HOME run while R200 = 1
        return not (a.moving and self._motion in MOVING)  # not while still moving

    def _check_timeout(self, ts: float, out: StepOut) -> None:
        a = self._active
        if a is None or ts - a.t0 <= self._timeout or not self._may_time_out(a):
            return
        a.warned = True
        why = (
            "robot never moved"
            if a.spec is not None and a.spec.motion and not a.moving
            else "no IR200 status"
        )
        out.warn(
            f"never completed: {a.decoded.text} ({why} {self._timeout:g} s after R200 = 1)",
            kind="never_completed",
            code=a.decoded.code,
        )
