"""frame_details: the one text of a frame's fields (decode's and the details pane's), each
line with the ADU bytes it describes. Byte tables: Modbus/TCP and RTU ADUs of the spec."""

from __future__ import annotations

import pytest

from mbmon.details import frame_details
from mbmon.model import Direction, Frame, Stream, Transport
from mbmon.protocol.crc import add_crc
from mbmon.protocol.pdu import decode_pdu

TCP = Stream(0, Transport.TCP, "c", "s")
RTU = Stream(1, Transport.RTU, "bus", "bus")


def _frame(stream: Stream, adu: bytes, response: bool) -> Frame:
    if stream.transport is Transport.TCP:
        unit, tid, pdu = adu[6], int.from_bytes(adu[:2]), adu[7:]
        crc = None
    else:
        unit, tid, pdu, crc = adu[0], None, adu[1:-2], True
    d = Direction.S2C if response else Direction.C2S
    return Frame(0.0, stream, d, unit, tid, decode_pdu(pdu, response), adu, crc)


def _spans(frame: Frame) -> dict[str, bytes]:
    """Each detail's name -> the bytes of the ADU its span covers."""
    out = {}
    for text, span in frame_details(frame):
        name = text.split(":", 1)[0]
        out[name] = frame.raw[span[0] : span[1]] if span is not None else None
    return out


@pytest.mark.parametrize(
    ("adu", "response", "expected"),
    [
        # Read Holding Registers 107..109 (spec example), MBAP tid 1 unit 17
        (
            bytes.fromhex("0001 0000 0006 11 03 006B 0003"),
            False,
            {"unit": b"\x11", "transaction id": b"\x00\x01", "kind": b"\x03",
             "address": b"\x00\x6b", "count": b"\x00\x03"},
        ),
        # its answer: byte count 6, three registers
        (
            bytes.fromhex("0001 0000 0009 11 03 06 022B 0000 0064"),
            True,
            {"byte count": b"\x06", "values": bytes.fromhex("022B00000064")},
        ),
        # Write Multiple Registers R201..R203 (the manual's JOG example)
        (
            bytes.fromhex("0002 0000 000D 01 10 00C9 0003 06 0003 0000 0001"),
            False,
            {"address": b"\x00\xc9", "count": b"\x00\x03", "byte count": b"\x06",
             "values": bytes.fromhex("000300000001")},
        ),
        # Write Single Coil 0 ON
        (
            bytes.fromhex("0003 0000 0006 01 05 0000 FF00"),
            False,
            {"address": b"\x00\x00", "values": b"\xff\x00"},
        ),
        # an exception answer: 83 02
        (
            bytes.fromhex("0004 0000 0003 01 83 02"),
            True,
            {"exception code": b"\x02", "kind": b"\x83"},
        ),
    ],
)  # fmt: skip
def test_tcp_fields_and_their_bytes(adu: bytes, response: bool, expected: dict) -> None:
    spans = _spans(_frame(TCP, adu, response))
    for name, raw in expected.items():
        assert spans[name] == raw, (name, spans)
    assert spans["framing"] is None


def test_rtu_unit_and_crc_bytes() -> None:
    adu = add_crc(bytes.fromhex("01 03 0000 000A"))
    frame = _frame(RTU, adu, False)
    spans = _spans(frame)
    assert spans["unit"] == b"\x01"
    assert spans["CRC"] == adu[-2:]
    assert spans["address"] == b"\x00\x00" and spans["count"] == b"\x00\x0a"
    texts = [t for t, _ in frame_details(frame)]
    assert texts[:4] == ["framing: RTU ADU", "unit: 1", "CRC: ok", "kind: request"]


def test_response_meaning_names_the_request_addresses() -> None:
    request = _frame(TCP, bytes.fromhex("0001 0000 0006 01 03 00C8 0002"), False)
    answer = _frame(TCP, bytes.fromhex("0001 0000 0007 01 03 04 0001 0002"), True)
    alone = dict(t.split(": ", 1) for t, _ in frame_details(answer))
    paired = dict(t.split(": ", 1) for t, _ in frame_details(answer, request=request.pdu))
    assert alone["meaning"] == "Read Holding Registers = 1, 2"
    assert paired["meaning"] == "Read Holding Registers 200..201 = 1, 2"


def test_notes_come_last_without_bytes() -> None:
    frame = _frame(TCP, bytes.fromhex("0001 0000 0006 01 03 00C8 0002"), False)
    details = frame_details(frame, ("R200 execute", "two"))
    assert details[-2:] == [("note: R200 execute", None), ("note: two", None)]
