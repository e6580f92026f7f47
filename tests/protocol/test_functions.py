"""The one function-code table and the write helpers the proxy's guard reads."""

from __future__ import annotations

from mbmon.format import function_name
from mbmon.model import Kind
from mbmon.protocol import functions, pairing, pdu
from mbmon.protocol.functions import FUNCTIONS, WriteSpan, is_write, write_spans
from mbmon.protocol.pdu import (
    decode_pdu,
    encode_read_request,
    encode_write_multiple_request,
    encode_write_single,
    pdu_length,
    table_of,
)
from mbmon.semantics import annotate


def req(raw: bytes):  # type: ignore[no-untyped-def]
    return decode_pdu(raw, False)


def test_every_layer_reads_the_one_table() -> None:
    # names (pdu, format), tables (pdu, annotate), pairing sets all come from FUNCTIONS
    assert pdu.FUNCTION_NAMES == {c: f.name for c, f in FUNCTIONS.items()}
    assert all(function_name(c) == f.name for c, f in FUNCTIONS.items())
    assert function_name(0x41) == "Function 0x41"
    for code, f in FUNCTIONS.items():
        assert table_of(code) == f.table
        assert annotate._TABLE.get(code) == (functions.PROFILE_TABLE[f.table] if f.table else None)
    assert set(pdu._DECODERS) <= set(FUNCTIONS)
    assert pairing._PAIR_ALWAYS is functions.PAIR_ALWAYS


def test_table_keeps_the_former_values() -> None:
    # the tables the five files held before, verbatim
    assert annotate._TABLE == {
        0x01: "coils", 0x05: "coils", 0x0F: "coils", 0x02: "discrete_inputs",
        0x03: "holding_registers", 0x06: "holding_registers", 0x10: "holding_registers",
        0x16: "holding_registers", 0x17: "holding_registers", 0x04: "input_registers",
    }  # fmt: skip
    assert {c for c, f in FUNCTIONS.items() if f.bits} == {1, 2, 5, 15}
    assert {c for c, f in FUNCTIONS.items() if f.read} == {1, 2, 3, 4, 0x17}
    assert pdu_length(bytes([0x08, 0x00, 0x00]), False) is None
    assert pdu_length(bytes([0x08, 0x00, 0x15]), True) is None
    assert pdu_length(bytes([0x08, 0x00, 0x01]), True) == 5
    assert pdu_length(bytes([0x18, 0x00, 0x06]), True) == 9
    assert pdu_length(bytes([0x2B, 0x0E]), False) == 4
    assert pdu_length(bytes([0x2B, 0x0D]), False) is None
    assert pdu_length(bytes([0x2B, 0x0E]), True) is None
    assert pdu_length(bytes([0x41]), False) is None


def test_is_write() -> None:
    writes = [
        encode_write_single(5, 10, True),
        encode_write_single(6, 10, 7),
        encode_write_multiple_request(0x0F, 3, [1, 0, 1]),
        encode_write_multiple_request(0x10, 200, [1, 2]),
        bytes.fromhex("16 00 04 00 F2 00 25"),
        bytes.fromhex("17 00 03 00 06 00 0E 00 03 06 00 FF 00 FF 00 FF"),
        bytes.fromhex("15 0D 06 00 04 00 07 00 03 06 AF 04 BE 10 0D"),
    ]
    assert all(is_write(req(w)) for w in writes)
    assert not is_write(req(encode_read_request(3, 0, 10)))
    assert not is_write(decode_pdu(encode_write_single(6, 10, 7), True))  # the echo
    assert not is_write(req(bytes([0x86, 0x00, 0x01, 0x00, 0x02])))  # exception bit


def test_write_spans() -> None:
    assert write_spans(req(encode_write_single(5, 10, True))) == (WriteSpan("coil", 10, 1),)
    assert write_spans(req(encode_write_single(6, 10, 7))) == (WriteSpan("hr", 10, 1),)
    assert write_spans(req(encode_write_multiple_request(0x0F, 3, [1, 0, 1]))) == (
        WriteSpan("coil", 3, 3),
    )
    assert write_spans(req(encode_write_multiple_request(0x10, 200, [1, 2]))) == (
        WriteSpan("hr", 200, 2),
    )
    assert write_spans(req(bytes.fromhex("16 00 04 00 F2 00 25"))) == (WriteSpan("hr", 4, 1),)
    rw = req(bytes.fromhex("17 00 03 00 06 00 0E 00 03 06 00 FF 00 FF 00 FF"))
    assert rw.kind is Kind.REQUEST
    assert write_spans(rw) == (WriteSpan("hr", 14, 3),)  # the write part, not the read
    wf = req(bytes.fromhex("15 0D 06 00 04 00 07 00 03 06 AF 04 BE 10 0D"))
    assert write_spans(wf) == (WriteSpan("file", 7, 3, file=4),)
    assert write_spans(req(encode_read_request(3, 0, 10))) == ()
    assert write_spans(req(bytes([0x06, 0x00]))) == ()  # truncated: no address


def test_quantity_limits_and_shapes_are_the_spec_s() -> None:
    limits = {c: (f.shape, f.max_count, f.max_write_count) for c, f in FUNCTIONS.items() if f.shape}
    assert limits == {
        0x01: ("read", 2000, None), 0x02: ("read", 2000, None),
        0x03: ("read", 125, None), 0x04: ("read", 125, None),
        0x05: ("write_single", None, None), 0x06: ("write_single", None, None),
        0x0F: ("write_multiple", 1968, None), 0x10: ("write_multiple", 123, None),
        0x16: ("mask_write", None, None), 0x17: ("read_write", 125, 121),
    }  # fmt: skip
    assert functions.PAIR_ALWAYS == {0x01, 0x02, 0x08, 0x14}
    assert functions.PAIR_ON_COUNT == {0x03, 0x04, 0x17}


def test_mask_write_is_the_spec_s_example() -> None:
    # Modbus Application Protocol 6.16: current 0x12, AND 0xF2, OR 0x25 -> 0x17
    assert functions.mask_write(0x12, 0xF2, 0x25) == 0x17
    assert functions.mask_write(0xFFFF, 0x0000, 0x1234) == 0x1234
    assert functions.mask_write(0xABCD, 0xFFFF, 0x1234) == 0xABCD
