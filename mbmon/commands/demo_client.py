"""``mbmon demo``'s client: the manual's program and a guarded write through the proxy,
narrated into the hub, and the closing words on what it did."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

#: The write the demo's guard refuses: the robot's system inputs SI1..SI256 (Table 12).
GUARD_SPEC = "coil:0-255"
#: Pauses (seconds) so that a human can follow the live screen: after each request
#: (not the polls of a running motion), and at the start of each part.
STEP_PAUSE = 0.12
PART_PAUSE = 0.9
#: The proxy's gateway timeout in the demo (the pipeline waits one second longer).
PROXY_TIMEOUT = 3.0


class _Stopped(Exception):
    """Ctrl-C or SIGTERM while the client runs."""


class DemoClient:
    """The client side of the demo: the program, the guarded write, the narration.

    Runs in its own thread (:meth:`run`). Narration goes into the hub as NOTICE
    events through ``say``; ``pause`` paces the steps. Results are kept for the
    closing summary: ``result`` (the program's), ``refused`` (the guard's answer
    code), ``error`` (why a step failed).
    """

    def __init__(
        self,
        host: str,
        port: int,
        say: Any,
        *,
        fast: bool,
        stop: threading.Event,
    ) -> None:
        self.host, self.port = host, port
        self.say = say
        self.fast = fast
        self.stop = stop
        self.result: Any = None
        self.refused: int | None = None
        self.ptp_status: int | None = None
        self.requests = 0
        self.finished: float | None = None  # time.monotonic() when the client was done
        self.error: str | None = None
        self._client: Any = None

    def pause(self, seconds: float) -> None:
        if self.stop.wait(0 if self.fast else seconds):
            raise _Stopped

    def on_part(self, part: str) -> None:
        """Before a part's first request: narrate it, give the eye time to read it."""
        text = _PARTS.get(part)
        if text is not None:
            self.say(text)
            self.pause(PART_PAUSE)

    def on_step(self, step: Any) -> None:
        """After each answered request: pace the step."""
        self.requests += 1
        polling = step.function == 4 and step.address == 524 and step.result == (2,)
        self.pause(0 if polling else STEP_PAUSE)
        if step.part == "5.4.5.2" and (step.function, step.address, step.values) == (16, 200, (1,)):
            self._ptp_status()

    def _ptp_status(self) -> None:
        """The one request the demo adds to §5.4.5.2: IR200 after the PTP's R200 = 1, so
        the PTP's outcome (accepted: 1 Success) is on the wire and in the log."""
        self.say(_PTP_STATUS)
        from mbmon.sim.program import ProgramError

        rr = self._client.read_input_registers(200, count=1, device_id=1)
        self.requests += 1
        if rr.isError():
            raise ProgramError(f"IR200 after the PTP: {rr}")
        self.ptp_status = int(rr.registers[0])
        self.pause(STEP_PAUSE)

    def run(self) -> None:
        from pymodbus.client import ModbusTcpClient

        from mbmon.sim.program import ProgramError, run_program

        client = ModbusTcpClient(self.host, port=self.port, timeout=PROXY_TIMEOUT + 1, retries=0)
        self._client = client
        try:
            if not client.connect():
                self.error = f"cannot connect to the proxy at {self.host}:{self.port}"
                return
            self.say(_INTRO)
            self.pause(PART_PAUSE)
            self.result = run_program(
                self.host,
                self.port,
                client=client,
                on_step=self.on_step,
                on_part=self.on_part,
                poll=0.1,
                timeout=20.0,
            )
            self.say(_GUARD)
            self.pause(PART_PAUSE)
            rr = client.write_coil(0, True, device_id=1)
            self.requests += 1
            self.refused = getattr(rr, "exception_code", None) if rr.isError() else 0
            self.pause(STEP_PAUSE)
            if self.refused != 1:
                self.error = f"the guarded write of SI1 was not refused (answer {rr})"
        except _Stopped:
            self.error = "interrupted"
        except ProgramError as exc:
            self.error = str(exc)
        except Exception as exc:  # pymodbus raises its own exceptions on a lost connection
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            client.close()
            self.finished = time.monotonic()


#: The narration, one NOTICE per part (short: a live screen row is about 100 characters).
_INTRO = (
    "demo §5.4.5.2: read speed IR100, R100 = 90 %, read DI[1..8], write DO[1..5], "
    "PTP {A1 90} via R200/R201.., poll IR524 until Idle"
)
_PTP_STATUS = "demo: one read the program leaves out: IR200, the PTP's status (1 Success, 2 Fail)"
_GUARD = (
    f"demo guard: the proxy refuses writes to SI1..SI256 ({GUARD_SPEC}); "
    "the client writes SI1 Start = ON"
)
_PARTS = {
    "LIN": "demo LIN {X -300, Y 300, Z 400, A 180, B 0, C 90} Vel=1000mm/s: R200 = 0, "
    "R201.., R200 = 1, IR200, IR524, X..C in IR400..IR411",
    "Set PR": "demo Set PR: $PR[2] = {X 90, Y 0, Z 0, A 0, B 0, C 0} (command 100), IR200",
    "Get PR": "demo Get PR[2] (command 200): the robot returns PR[2] in IR202..IR215",
    "JOG": "demo JOG A1 +: moves while R200 stays 1; R200 = 0 stops it",
}


def closing(log: Path, client: DemoClient, elapsed: float, *, quiet: bool) -> None:
    """What the demo did and how to look at the log again (stdout, after the live screen)."""
    result = client.result
    status = result.statuses
    name = str(log)
    if any(c.isspace() for c in name):
        name = repr(name)
    lines = [
        "",
        f"mbmon demo: done in {elapsed:.1f} s, {client.requests} requests through the proxy",
        f"  PTP {{A1 90}}: status {client.ptp_status}, A1 = {result.joints[0]:g}°; "
        f"LIN status {status.get('LIN')}, X Y Z = {' '.join(f'{v:g}' for v in result.pose[:3])}",
        f"  Set PR {status.get('Set PR')}, Get PR {status.get('Get PR')} (1 = success); "
        f"JOG moved A1 {result.jog_moved:.2f}° ({result.jog_from:g} → {result.jog_to:g}°)",
        f"  the write of SI1 Start was refused by the guard (exception {client.refused:02X})",
        f"  log: {name}",
        "",
        "next:",
        f"  mbmon replay {name}                 the run again, as it was shown",
        f"  mbmon replay {name} --grep Guard    the refused write in the audit",
        f"  mbmon info {name}                   what the log holds",
        f"  mbmon replay {name} --serve         the recorded robot on 127.0.0.1:1502, for a client",
        f"  Foxglove: open {name} in https://app.foxglove.dev (or Foxglove desktop):",
        "    Log panel on /modbus/monitor, Plot on /hrss/state.a1, Raw Messages on /hrss/commands",
    ]
    if not quiet:
        print("\n".join(lines), flush=True)
