"""The RS485 test corpus shared by the decoder, ``read --rtu-raw``, ``sniff --serial``
and proxy tests: libmodbus's RTU unit-test session as bytes, the bad requests it
sends, and a simulated bus that delivers frames (with noise between them) at
the times a serial reader would see them: promptly, or in a USB adapter's
bursts.

Importable from any test (``pythonpath = ["tests"]`` in pyproject.toml).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mbmon.model import Direction, Frame, Noise
from mbmon.protocol.rtu import RtuDecoder

SESSION_FILE = Path(__file__).resolve().parent / "protocol" / "data" / "libmodbus_rtu_session.txt"


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def session() -> list[tuple[str, bytes]]:
    """libmodbus's RTU unit-test session: ('>' master or '<' slave, frame) in order."""
    out = []
    for line in SESSION_FILE.read_text().splitlines():
        if line and not line.startswith("#"):
            out.append((line[0], h(line[2:])))
    return out


def bus_directions(frames: list[tuple[str, bytes]]) -> list[tuple[Direction, bytes]]:
    """What a tap on the bus can tell of each frame's direction: the master's frames
    are requests, except one libmodbus sends on purpose that has the shape of the
    answer to the request before it (the pending request says "answer")."""
    out = []
    for who, raw in frames:
        d = Direction.C2S if who == ">" else Direction.S2C
        if raw == RESPONSE_SHAPED:
            d = Direction.S2C
        out.append((d, raw))
    return out


#: libmodbus's requests whose length fields disagree with their length (quantity 0
#: and byte count 0 with 6 data bytes), CRC correct, and the server's answers.
BAD_REQUESTS: list[tuple[bytes, bytes]] = [
    (h("11 10 01 60 00 00 00 02 2B 00 01 00 64 8C 88"), h("11 90 03 0D C4")),
    (h("11 0F 01 60 00 00 00 02 2B 00 01 00 64 59 63"), h("11 8F 03 05 F4")),
    (h("11 10 01 60 00 7C 06 02 2B 00 01 00 64 ED F9"), h("11 90 03 0D C4")),
    (h("11 0F 01 60 07 B1 06 02 2B 00 01 00 64 D3 EB"), h("11 8F 03 05 F4")),
    (h("11 17 01 60 00 00 00 00 00 01 02 12 34 A1 C7"), h("11 97 03 0F F4")),
]
#: A frame libmodbus's master sends that reads as the answer to its previous request.
RESPONSE_SHAPED = h("12 03 04 00 00 00 00 D8 F2")
#: A read with a bad CRC, then the good one.
BAD_CRC = h("11 03 01 60 00 01 87 79")
GOOD = h("11 03 01 60 00 01 87 78")

BAUD = 115200
CHAR = 11.0 / BAUD


@dataclass
class Delivered:
    """One read: its bytes and when the reader got them."""

    ts: float
    data: bytes


def wire(parts: list[bytes], gaps: list[float], start: float = 1000.0) -> list[tuple[float, int]]:
    """Each byte of ``parts`` with the time its last bit left the wire: part ``i``
    starts ``gaps[i]`` after the previous one ended (bytes back to back inside it)."""
    out = []
    t = start
    for part, gap in zip(parts, gaps, strict=True):
        t += gap
        for b in part:
            t += CHAR
            out.append((t, b))
    return out


def prompt(parts: list[bytes], gaps: list[float], start: float = 1000.0) -> list[Delivered]:
    """A reader that gets each part as one read when its last byte arrived."""
    out = []
    t = start
    for part, gap in zip(parts, gaps, strict=True):
        t += gap + len(part) * CHAR
        out.append(Delivered(t, part))
    return out


def bursts(bytes_at: list[tuple[float, int]], every: float = 0.016) -> list[Delivered]:
    """A USB adapter's delivery: what arrived on the wire is handed over every ``every`` s."""
    out: list[Delivered] = []
    if not bytes_at:
        return out
    first = bytes_at[0][0]
    slot = int((first - 0) // every)
    pending = bytearray()
    for t, b in bytes_at:
        s = int(t // every)
        if s != slot and pending:
            out.append(Delivered((slot + 1) * every, bytes(pending)))
            pending = bytearray()
        slot = s
        pending.append(b)
    if pending:
        out.append(Delivered((slot + 1) * every, bytes(pending)))
    return out


def drive(dec: RtuDecoder, reads: list[Delivered]) -> list[tuple[float, Frame | Noise]]:
    """Feed the reads and tick at every deadline before the next read, as the hub
    does; each item comes with the time it was given out."""
    out: list[tuple[float, Frame | Noise]] = []
    now = 0.0
    for r in reads:
        while (dl := dec.next_deadline()) is not None and dl < r.ts:
            out += [(dl, x) for x in dec.tick(dl)]
        out += [(r.ts, x) for x in dec.feed(r.data, r.ts)]
        now = r.ts
    while (dl := dec.next_deadline()) is not None:
        out += [(dl, x) for x in dec.tick(dl)]
        now = dl
    out += [(now, x) for x in dec.flush(now)]
    return out


def arrival_of_each_byte(reads: list[Delivered]) -> list[float]:
    """The read time of every byte, in stream order."""
    return [r.ts for r in reads for _ in r.data]
