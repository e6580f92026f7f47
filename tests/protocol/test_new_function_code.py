"""Where a new function code goes: one row of the function-code table.

A user-defined code (0x41, a holding-register read) registered with
:func:`mbmon.protocol.functions.register` -- the row lives here, in the test, not
in the shipped table -- decodes, frames over RTU, pairs, is annotated and prints
through ``mbmon read`` like 0x03, with no other file touched.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.model import Frame, Kind, Stream, Transport
from mbmon.protocol import functions
from mbmon.protocol.functions import FUNCTIONS, FunctionCode, register, unregister
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import decode_pdu, pdu_length, table_of
from mbmon.protocol.rtu import RtuDecoder, encode_rtu

REPO = Path(__file__).resolve().parents[2]

#: the one row a user adds: 0x41 reads holding registers like 0x03
TOY = FunctionCode(
    0x41, "Toy Read", 5, (1, 2), "holding_register", read=True, shape="read", max_count=125
)
TOY_ROW = (
    'FunctionCode(0x41, "Toy Read", 5, (1, 2), "holding_register", read=True, '
    'shape="read", max_count=125)'
)

REQUEST = bytes([0x41, 0x00, 0x10, 0x00, 0x02])  # 2 registers from 16
ANSWER = bytes([0x41, 0x04, 0x00, 0x07, 0x00, 0x08])
TOO_MANY = bytes([0x41, 0x00, 0x10, 0x00, 0xC8])  # 200 registers: past the row's limit


@pytest.fixture
def toy() -> Iterator[FunctionCode]:
    assert 0x41 not in FUNCTIONS, "the shipped table must not hold the toy code"
    # decoded before the row exists: user-defined, its bytes kept as data
    assert decode_pdu(REQUEST, False).fields["data"] == REQUEST[1:]
    register(TOY)
    try:
        yield TOY
    finally:
        unregister(0x41)


def test_a_registered_read_decodes_like_0x03(toy: FunctionCode) -> None:
    req = decode_pdu(REQUEST, False)
    assert (req.fc, req.kind, req.address, req.count, req.malformed) == (
        0x41,
        Kind.REQUEST,
        16,
        2,
        None,
    )
    resp = decode_pdu(ANSWER, True, req)
    assert (resp.byte_count, resp.values, resp.malformed) == (4, (7, 8), None)
    assert decode_pdu(TOO_MANY, False).malformed == "count 200 outside 1..125"
    assert pdu_length(REQUEST, False) == 5 and pdu_length(ANSWER, True) == 6
    assert table_of(0x41) == "holding_register"
    assert 0x41 in functions.PAIR_ON_COUNT  # answers are checked against the count


def test_every_derived_table_knows_a_registered_code(toy: FunctionCode) -> None:
    from mbmon import format as fmt
    from mbmon import jsonfmt
    from mbmon.protocol import rtu
    from mbmon.semantics import annotate

    assert rtu._REQ_RULES[0x41] == 8 and rtu._RESP_RULES[0x41] == (2, 5)  # ADU sizes
    assert 0x41 in annotate._READ_FCS and annotate._TABLE[0x41] == "holding_registers"
    assert 0x41 in jsonfmt._READS and fmt.function_name(0x41) == "Toy Read"


def test_unregister_forgets_the_row(toy: FunctionCode) -> None:
    assert decode_pdu(REQUEST, False).count == 2
    unregister(0x41)
    try:
        # the decode cache was emptied: the same bytes are user-defined again
        assert decode_pdu(REQUEST, False).count is None
        assert pdu_length(REQUEST, False) is None
    finally:
        register(TOY)  # the fixture unregisters it


def test_a_registered_read_frames_over_rtu(toy: FunctionCode) -> None:
    # the RTU framer cuts ADUs by the row's lengths: back to back, no gap between them
    dec = RtuDecoder(Stream(1, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0"))
    wire = encode_rtu(1, REQUEST) + encode_rtu(1, ANSWER)
    out = [*dec.feed(wire, 1.0), *dec.flush(2.0)]
    frames = [f for f in out if isinstance(f, Frame)]
    assert [(f.pdu.fc, f.pdu.kind, f.crc_ok) for f in frames] == [
        (0x41, Kind.REQUEST, True),
        (0x41, Kind.RESPONSE, True),
    ]
    assert frames[1].pdu.values == (7, 8)


def _capture(path: Path) -> None:
    conv = TcpConversation("10.0.0.10:50000", "10.0.0.2:502")
    with PcapWriter(path) as out:
        ts = 1_700_000_000.0
        for frame in conv.open():
            out.write(ts, frame)
        out.write(ts + 0.010, conv.send(True, encode_adu(1, 1, REQUEST)))
        out.write(ts + 0.012, conv.send(False, encode_adu(1, 1, ANSWER)))
        out.write(ts + 0.020, conv.send(True, encode_adu(2, 1, TOO_MANY)))
        for frame in conv.close():
            out.write(ts + 0.030, frame)


def _read(path: Path, *, with_row: bool) -> list[str]:
    """``mbmon read`` of ``path`` in a process that registers the toy row first (or not).

    Forced pure (``MBMON_NO_EXTENSIONS=1``), so that the test reads the same path
    whether the extension is built or not (the core hands codes above 0x10 to
    ``decode_pdu`` and takes names from ``format``, but its own fast decode of
    0x01..0x10 is compiled and does not read the table); ``-c 100`` bounds it.
    """
    register_row = (
        f"from mbmon.protocol.functions import FunctionCode, register; register({TOY_ROW}); "
        if with_row
        else ""
    )
    code = f"import sys; {register_row}from mbmon.cli import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run(
        [sys.executable, "-c", code, "read", "-c", "100", str(path)],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=REPO,
        env={**os.environ, "MBMON_NO_EXTENSIONS": "1"},
    )
    assert done.returncode == 0, done.stderr
    return [line.split("  ", 1)[1] for line in done.stdout.splitlines()]


def test_mbmon_read_prints_a_registered_read(tmp_path: Path) -> None:
    path = tmp_path / "toy.pcap"
    _capture(path)
    before = _read(path, with_row=False)
    assert "[u1 t1]  41 00 10 00 02  | Function 0x41" in before[1]
    lines = _read(path, with_row=True)
    assert lines[1].endswith("[u1 t1]  41 00 10 00 02  | Toy Read 16..17")
    # paired: the answer takes its address from the request, with the latency
    assert lines[2].endswith("[u1 t1]  41 04 00 07 00 08  | Toy Read 16..17 = 7, 8 (2.0 ms)")
    assert lines[3].endswith("| Toy Read 16..215 [malformed: count 200 outside 1..125]")
    assert lines[-1] == "-- No response to Toy Read (record #3)"


def test_a_replaced_public_row_is_honoured_by_the_fast_path() -> None:
    # a device that gives 0x06 a layout of its own (no shape) and one that allows 10
    # registers per read: the well-formed fast path follows the replaced rows, and
    # the shipped rows come back afterwards
    shipped6, shipped3 = FUNCTIONS[0x06], FUNCTIONS[0x03]
    write = bytes([0x06, 0x00, 0x01, 0x00, 0x02])
    narrow = bytes([0x03, 0x00, 0x00, 0x00, 0x0B])  # 11 registers
    assert decode_pdu(write, False).values == (2,)
    register(FunctionCode(0x06, "Vendor Write", 5, 5))
    register(dataclasses.replace(shipped3, max_count=10))
    try:
        custom = decode_pdu(write, False)
        assert (custom.address, custom.values, custom.fields["data"]) == (None, None, write[1:])
        assert decode_pdu(narrow, False).malformed == "count 11 outside 1..10"
    finally:
        register(shipped6)
        register(shipped3)
    assert decode_pdu(write, False).values == (2,)
    assert decode_pdu(narrow, False).malformed is None


@pytest.mark.parametrize(
    ("row", "reason"),
    [
        (FunctionCode(0x00, "Zero", 1, 1), "outside 1..127"),
        (FunctionCode(0x81, "High", 1, 1), "outside 1..127"),
        (FunctionCode(0x42, "Odd", 5, 5, shape="scatter"), "unknown shape 'scatter'"),
        (FunctionCode(0x42, "Bits", 7, 7, bits=True, shape="mask_write"), "for registers"),
    ],
)
def test_register_refuses_a_row_it_cannot_use(row: FunctionCode, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        register(row)
    assert row.code not in FUNCTIONS or FUNCTIONS[row.code] is not row
