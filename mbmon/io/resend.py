"""``replay --to``: the recorded requests sent again to a live server, its answers compared.

What this module owns:

- :func:`changes_server`: which requests change the server (the writes of the
  one function-code table, :func:`mbmon.protocol.functions.is_write`, plus the
  diagnostics that restart, clear or silence a device); they are skipped unless
  the caller allows writes;
- :func:`compare`: the differences between a recorded and a live answer to one
  request, in words (pure);
- :class:`LiveClient`: one Modbus/TCP connection (blocking socket, answers
  matched by transaction id, framed by mbmon's MBAP decoder);
- :func:`resend`: the loop over the exchanges, paced like the original when a
  speed is given, printing one line per request whose answers differ and
  returning a :class:`ResendReport`.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import IO

from mbmon.io.emulate import TABLE_NAMES
from mbmon.io.exchanges import Exchange
from mbmon.model import Direction, Frame, Kind, Pdu, Stream, Transport
from mbmon.protocol.functions import FUNCTIONS, SHAPE, is_write
from mbmon.protocol.pdu import EXCEPTION_NAMES, FUNCTION_NAMES, decode_pdu, table_of

__all__ = [
    "LiveClient",
    "LiveError",
    "ResendReport",
    "changes_server",
    "compare",
    "resend",
]

#: 0x08 sub-functions that change the device: restart, change delimiter, listen only,
#: clear counters, clear overrun
_DIAG_CHANGES = frozenset({0x01, 0x03, 0x04, 0x0A, 0x14})
#: how many values a difference line lists before "..."
MAX_LISTED = 8


class LiveError(Exception):
    """The live server cannot be reached or the connection broke (exit status 1)."""


def changes_server(pdu: Pdu) -> bool:
    """Whether re-sending this request would change the server (a write, or a
    diagnostic that restarts, clears or silences it)."""
    if is_write(pdu):
        return True
    return pdu.fc == 0x08 and pdu.fields.get("sub_function") in _DIAG_CHANGES


def _answer_text(pdu: Pdu | None) -> str:
    if pdu is None:
        return "no answer"
    if pdu.kind is Kind.EXCEPTION:
        code = pdu.exception_code or 0
        return f"exception {code:02X} ({EXCEPTION_NAMES.get(code, 'unknown')})"
    return "values" if pdu.values is not None else "an answer"


def _hex(raw: bytes) -> str:
    return raw.hex(" ").upper()


def compare(request: Pdu, recorded: Pdu | None, live: Pdu | None) -> list[str]:
    """How the live answer differs from the recorded one (empty: identical).

    Read answers are compared address by address (``holding register 300:
    recorded 42, live 7``; bits past the requested count are padding, not
    values); exceptions by code; an answer against an exception
    or no answer in words; anything else by its bytes.
    """
    if recorded is None and live is None:
        return []
    if recorded is not None and live is not None and recorded.raw == live.raw:
        return []
    if recorded is None or live is None or recorded.kind is not live.kind:
        return [f"recorded {_answer_text(recorded)}, live {_answer_text(live)}"]
    if recorded.kind is Kind.EXCEPTION:
        return [f"recorded {_answer_text(recorded)}, live {_answer_text(live)}"]
    table = table_of(request.fc)
    if (
        table is not None
        and SHAPE.get(request.fc) in ("read", "read_write")
        and request.address is not None
        and recorded.values is not None
        and live.values is not None
    ):
        rv, lv = recorded.values, live.values
        if request.count is not None and FUNCTIONS[request.fc].bits:  # bit reads: padding
            rv, lv = rv[: request.count], lv[: request.count]
        out: list[str] = []
        if len(rv) != len(lv):
            out.append(f"recorded {len(rv)} values, live {len(lv)}")
        name = TABLE_NAMES[table][:-1]  # "holding register"
        diffs = [
            f"{request.address + i} recorded {a}, live {b}"
            for i, (a, b) in enumerate(zip(rv, lv, strict=False))
            if a != b
        ]
        if diffs:
            shown = "; ".join(diffs[:MAX_LISTED])
            more = f"; ... {len(diffs) - MAX_LISTED} more" if len(diffs) > MAX_LISTED else ""
            verb = "s differ" if len(diffs) != 1 else " differs"
            out.append(f"{len(diffs)} {name}{verb}: {shown}{more}")
        return out  # the same values: only padding bits past the count differ
    return [f"recorded {_hex(recorded.raw)}, live {_hex(live.raw)}"]


def _describe_request(unit: int, pdu: Pdu) -> str:
    name = FUNCTION_NAMES.get(pdu.fc, f"function 0x{pdu.fc:02X}")
    where = ""
    if pdu.address is not None:
        last = pdu.address + (pdu.count or 1) - 1
        where = f" {pdu.address}" if last == pdu.address else f" {pdu.address}..{last}"
    return f"unit {unit} {pdu.fc:02X} {name}{where}"


# --------------------------------------------------------------------------- the live side


class LiveClient:
    """One Modbus/TCP connection to a live server; :meth:`ask` sends a PDU and
    returns the answer's PDU (``None`` after ``timeout`` seconds without it)."""

    def __init__(self, host: str, port: int, timeout: float = 3.0) -> None:
        from mbmon.protocol.mbap import MbapDecoder

        self.host, self.port, self.timeout = host, port, timeout
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout)
        except OSError as exc:
            raise LiveError(f"cannot connect to {host}:{port}: {exc.strerror or exc}") from None
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        stream = Stream(0, Transport.TCP, "replay", f"{host}:{port}")
        self._decoder = MbapDecoder(stream, Direction.S2C)
        self._tid = 0
        self._early: list[Frame] = []

    def close(self) -> None:
        self._sock.close()

    def ask(self, unit: int, pdu: bytes, request: Pdu) -> Pdu | None:
        """Send ``pdu`` to ``unit``; the answer decoded with ``request`` (bits trimmed)."""
        from mbmon.protocol.mbap import encode_adu

        self._tid = (self._tid + 1) & 0xFFFF
        tid = self._tid
        try:
            self._sock.sendall(encode_adu(tid, unit, pdu))
        except OSError as exc:
            why = exc.strerror or exc
            raise LiveError(f"{self.host}:{self.port}: send failed: {why}") from None
        deadline = time.monotonic() + self.timeout
        while True:
            for frame in self._decoder_frames():
                if frame.tid == tid:
                    return decode_pdu(frame.pdu.raw, response=True, request=request)
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._sock.settimeout(left)
            try:
                data = self._sock.recv(65536)
            except TimeoutError:
                return None
            except OSError as exc:
                raise LiveError(f"{self.host}:{self.port}: {exc.strerror or exc}") from None
            if not data:
                raise LiveError(f"{self.host}:{self.port} closed the connection")
            self._early.extend(
                f for f in self._decoder.feed(data, time.time()) if isinstance(f, Frame)
            )

    def _decoder_frames(self) -> list[Frame]:
        frames, self._early = self._early, []
        return frames  # answers to earlier, timed-out requests are dropped here


# --------------------------------------------------------------------------- the loop


@dataclass(slots=True)
class ResendReport:
    """What a re-send found."""

    sent: int = 0
    same: int = 0
    different: int = 0
    live_unanswered: int = 0
    skipped_writes: int = 0
    #: ``(exchange, live answer, differences)`` of every request whose answers differ
    differences: list[tuple[Exchange, Pdu | None, list[str]]] = field(default_factory=list)

    def summary(self, target: str, writes: bool) -> list[str]:
        """The closing lines: counts, and the writes that were not sent."""
        lines = [
            f"re-sent {self.sent} recorded requests to {target}: {self.same} answered as "
            f"recorded, {self.different} differently ({self.live_unanswered} not answered live)"
        ]
        if self.skipped_writes and not writes:
            lines.append(
                f"{self.skipped_writes} recorded writes not sent (they can move a robot: "
                "--writes sends them)"
            )
        return lines


def resend(
    exchanges: Iterable[Exchange],
    client: LiveClient,
    *,
    writes: bool = False,
    speed: float | None = None,
    out: IO[str] | None = None,
    pace: Callable[[float], None] | None = None,
    report: ResendReport | None = None,
) -> ResendReport:
    """Send every recorded request again (writes only when ``writes``), in recorded
    order, one at a time; ``speed`` paces them like the original (``None``: as fast
    as answers come). A line per differing request goes to ``out``. ``report``
    (default: a new one) is filled as requests go, so a caller that catches
    :class:`LiveError` still has the figures so far."""
    if report is None:
        report = ResendReport()
    if pace is None and speed is not None:
        from mbmon.filters import Pacer

        pace = Pacer(speed).wait
    for ex in exchanges:
        request = ex.request
        if not writes and changes_server(request):
            report.skipped_writes += 1
            continue
        if pace is not None:
            pace(ex.ts)
        live = client.ask(ex.unit, request.raw, request)
        report.sent += 1
        if live is None:
            report.live_unanswered += 1
        diffs = compare(request, ex.response, live)
        if not diffs:
            report.same += 1
            continue
        report.different += 1
        report.differences.append((ex, live, diffs))
        if out is not None:
            head = f"#{ex.index} {_describe_request(ex.unit, request)}: "
            out.write(head + diffs[0] + "\n")
            for more in diffs[1:]:
                out.write(" " * len(head) + more + "\n")
            out.flush()
    return report
