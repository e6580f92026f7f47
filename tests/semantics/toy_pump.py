"""A toy device with a session, for the tests of the session plug-in (not shipped).

A dosing pump: the client writes a volume to R0 (``setpoint``) and 1 to R1
(``start``); the pump counts what it has dosed in IR0 (``dosed``). The session
follows that as a command: "DOSE 250 ml" executing when R1 = 1 is written,
success when a read of IR0 shows the setpoint reached, a warning when it has
not after :data:`TIMEOUT` seconds (said by :meth:`ToyPumpSession.tick`, on
time, while the line is silent). Its panel shows the setpoint written.

The profile is data only (:data:`PROFILE`); the session is this module's code,
registered by the test as ``toy_pump``.
"""

from __future__ import annotations

from types import MappingProxyType

from mbmon.model import Annotation, CommandUpdate, Kind, Phase, Stream, Transaction, TxStatus
from mbmon.protocol.functions import FUNCTIONS
from mbmon.semantics.session import Panel, Session, annotation

PROFILE = """\
[profile]
name = "toy-pump"
description = "a dosing pump (tests of the session plug-in)"
session = "toy_pump"

[[holding_registers]]
name = "setpoint"
address = 0
type = "u16"
unit = "ml"

[[holding_registers]]
name = "start"
address = 1
type = "u16"
enum = { 0 = "idle", 1 = "start" }

[[input_registers]]
name = "dosed"
address = 0
type = "u16"
unit = "ml"
"""

#: the same map without a session: a data-only profile
DATA_ONLY = PROFILE.replace('session = "toy_pump"\n', "").replace('"toy-pump"', '"toy-map"')

TIMEOUT = 5.0


class ToyPumpSession(Session):
    """The pump's dose as a command (see the module text)."""

    def __init__(self, stream: Stream, unit: int) -> None:
        super().__init__(stream, unit)
        self.setpoint: int | None = None
        self.unconfirmed = False
        self.started: float | None = None  # time of the running dose's R1 = 1
        self.warned = False

    def follow(self, tx: Transaction, notes: list[str]) -> Annotation:
        req, resp = tx.request, tx.response
        if req is None or req.pdu.kind is not Kind.REQUEST:
            return annotation(notes)
        pdu = req.pdu
        row = FUNCTIONS.get(pdu.fc)  # what the code is: the one function-code table
        if row is None:
            return annotation(notes)
        writes = row.shape == "write_single" and row.table == "holding_register"
        reads = row.shape == "read" and row.table == "input_register"
        commands = self.tick(
            tx.ts
        )  # overdue: said at the next step too (a file is read without ticks)
        state = None
        if writes and tx.status is TxStatus.PENDING and pdu.values:
            if pdu.address == 0:
                self.setpoint, self.unconfirmed = pdu.values[0], True
            elif pdu.address == 1 and pdu.values[0] == 1:
                self.started, self.warned = tx.ts, False
                commands.append(self._update(tx.ts, Phase.EXECUTING, None))
                notes.append(f"toy: dosing {self.setpoint} ml")
        elif writes and tx.status is TxStatus.ANSWERED and pdu.address == 0:
            self.unconfirmed = False
        elif reads and tx.status is TxStatus.ANSWERED and resp is not None:
            values = resp.pdu.values
            if pdu.address == 0 and values:
                state = {"dosed": float(values[0])}
                if self.started is not None and values[0] >= (self.setpoint or 0):
                    commands.append(self._update(tx.ts, Phase.SUCCESS, tx.ts - self.started))
                    self.started = None
        return annotation(notes, tuple(commands), state)

    def tick(self, now: float) -> list[CommandUpdate]:
        deadline = self.next_deadline()
        if deadline is None or now < deadline:
            return []
        self.warned = True
        return [self._update(now, Phase.WARNING, None, "never completed")]

    def next_deadline(self) -> float | None:
        if self.started is None or self.warned:
            return None
        return self.started + TIMEOUT

    def panel(self) -> Panel:
        if self.setpoint is None:
            return Panel("pump")
        return Panel("pump", (("R0", "setpoint", f"{self.setpoint} ml", not self.unconfirmed),))

    def _update(
        self, ts: float, phase: Phase, duration: float | None, why: str = ""
    ) -> CommandUpdate:
        text = f"DOSE {self.setpoint} ml" + (f": {why}" if why else "")
        return CommandUpdate(
            ts, self.stream, self.unit, phase, text, code=None, duration=duration,
            params=MappingProxyType({"setpoint": self.setpoint}),
        )  # fmt: skip
