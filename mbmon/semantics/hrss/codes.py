"""Which function codes touch which HRSS image, from the one function-code table, and
which motion states mean moving: shared by the session and its compiled-core support."""

from __future__ import annotations

from mbmon.protocol.functions import FUNCTIONS, derived

MOVING = (2, 3, 4)  # IR524 Running, Hold, Delay
#: what the session applies to the holding image when a request is seen: the codes
#: that write holding registers
WRITE_FCS: set[int] = set()
#: the reads whose answer goes to the holding image, and those that go to the input image
HOLDING_READS: set[int] = set()
INPUT_READS: set[int] = set()


@derived
def _from_table() -> None:
    for codes, table, writes in (
        (WRITE_FCS, "holding_register", True),
        (HOLDING_READS, "holding_register", False),
        (INPUT_READS, "input_register", False),
    ):
        codes.clear()
        codes.update(
            code
            for code, f in FUNCTIONS.items()
            if f.table == table and (f.writes if writes else f.read)
        )
