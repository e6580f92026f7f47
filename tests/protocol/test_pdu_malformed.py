"""Spec violations are decoded as far as possible and flagged with a specific reason."""

from __future__ import annotations

import pytest

from mbmon.model import Kind
from mbmon.protocol.pdu import (
    decode_pdu,
    encode_read_request,
    encode_write_multiple_request,
)


def h(text: str) -> bytes:
    return bytes.fromhex(text)


RW = "17 00 03 00 06 00 0E 00 03 06 00 FF 00 FF 00 FF"

# (pdu, response, paired request or None, the exact malformed text)
CASES = [
    ("", False, None, "empty PDU"),
    ("", True, None, "empty PDU"),
    ("00 01", False, None, "function code 0 is invalid"),
    ("83 02", False, None, "exception bit set in request function code 0x83"),
    ("81", True, None, "truncated: exception response needs 2 bytes, got 1"),
    ("81 02 00", True, None, "1 trailing byte"),
    ("03 00 6B 00", False, None, "truncated: 0x03 request needs 5 bytes, got 4"),
    ("03", False, None, "truncated: 0x03 request needs 5 bytes, got 1"),
    ("03 00 6B 00 03 00 00", False, None, "2 trailing bytes"),
    ("03 00 00 00 00", False, None, "count 0 outside 1..125"),
    ("03 00 00 00 7E", False, None, "count 126 outside 1..125"),
    ("04 00 00 00 7E", False, None, "count 126 outside 1..125"),
    ("01 00 00 07 D1", False, None, "count 2001 outside 1..2000"),
    ("02 00 00 00 00", False, None, "count 0 outside 1..2000"),
    ("03 FF FF 00 02", False, None, "address 65535 + count 2 exceeds 65536"),
    ("03", True, None, "truncated: 0x03 response needs 2 bytes, got 1"),
    ("03 06 00 01 00 02", True, None, "byte count 6 but 4 data bytes"),
    ("03 02 00 01 00 02", True, None, "byte count 2 but 4 data bytes"),
    ("03 04 00 01 00 02", True, "03 00 00 00 03", "byte count 4 but 3 registers need 6"),
    ("03 03 00 01 02", True, None, "odd byte count 3"),
    ("03 00", True, None, "byte count 0"),
    ("01 00", True, None, "byte count 0"),
    ("01 02 13 00", True, "01 01 2C 00 05", "byte count 2 but 5 bits need 1"),
    ("02 01 13", True, "02 01 2C 00 09", "byte count 1 but 9 bits need 2"),
    ("05 00 AC 12 34", False, None, "coil value 0x1234 is not 0xFF00/0x0000"),
    ("05 00 AC 00 01", True, None, "coil value 0x0001 is not 0xFF00/0x0000"),
    ("06 00 01 00", True, None, "truncated: 0x06 response needs 5 bytes, got 4"),
    ("07", True, None, "truncated: 0x07 response needs 2 bytes, got 1"),
    ("07 00", False, None, "1 trailing byte"),
    ("08 00", False, None, "truncated: 0x08 request needs 3 bytes, got 2"),
    ("08 00 0A 00", False, None, "truncated: 0x08 request needs 5 bytes, got 4"),
    ("08 00 0A 00 00 00 00", True, None, "2 trailing bytes"),
    ("08 00 00 A5 38", True, "08 00 00 A5 37", "echo differs from request"),
    ("0B FF FF 01", True, None, "truncated: 0x0B response needs 5 bytes, got 4"),
    ("0C 03 00 00 01", True, None, "byte count 3 below 6"),
    ("0F 00 13 00 0A 01 CD", False, None, "byte count 1 but 10 bits need 2"),
    ("0F 00 13 00 0A 02 CD", False, None, "byte count 2 but 1 data bytes"),
    ("0F 00 13 00 0A", False, None, "truncated: 0x0F request needs 6 bytes, got 5"),
    ("0F 00 13 00 00", True, None, "count 0 outside 1..1968"),
    ("10 00 01 00 02 04 00 0A", False, None, "byte count 4 but 2 data bytes"),
    ("10 00 01 00 02 02 00 0A", False, None, "byte count 2 but 2 registers need 4"),
    ("10 00 01 00 7C", True, None, "count 124 outside 1..123"),
    ("10 00 01 00", True, None, "truncated: 0x10 response needs 5 bytes, got 4"),
    ("11", True, None, "truncated: 0x11 response needs 2 bytes, got 1"),
    ("11 03 01 FF", True, None, "byte count 3 but 2 data bytes"),
    ("14 07 05 00 04 00 01 00 02", False, None, "reference type 5 is not 6"),
    ("14 07 06 00 04 27 10 00 02", False, None, "record number 10000 exceeds 9999"),
    (
        "14 08 06 00 04 00 01 00 02 00",
        False,
        None,
        "byte count 8 is not a multiple of 7",
    ),
    (
        "14 04 03 06 0D FE",
        True,
        "14 07 06 00 04 00 01 00 02",
        "record of 1 words but 2 requested",
    ),
    ("14 04 05 06 0D FE", True, None, "sub-response 1 truncated"),
    ("14 02 00 00", True, None, "sub-response 1 has length 0"),
    (
        "15 0D 06 00 04 00 07 00 03 06 AF 04 BE 10 0E",
        True,
        "15 0D 06 00 04 00 07 00 03 06 AF 04 BE 10 0D",
        "echo differs from request",
    ),
    ("15 09 06 00 04 00 07 00 03 06 AF", False, None, "sub-request 1 truncated"),
    ("16 00 04 00 F2 00", False, None, "truncated: 0x16 request needs 7 bytes, got 6"),
    ("17 00 03 00 7E 00 0E 00 01 02 00 FF", False, None, "read count 126 outside 1..125"),
    (
        "17 00 03 00 06 00 0E 00 01 04 00 FF 00 FF",
        False,
        None,
        "write byte count 4 but 1 registers need 2",
    ),
    ("17 00 03 00 06 00 0E 00", False, None, "truncated: 0x17 request needs 10 bytes, got 8"),
    ("17 04 00 FE 0A CD", True, RW, "byte count 4 but 6 registers need 12"),
    ("18 04", False, None, "truncated: 0x18 request needs 3 bytes, got 2"),
    ("18 00 04 00 02 01 B8", True, None, "byte count 4 but fifo count 2 needs 6"),
    ("18 00", True, None, "truncated: 0x18 response needs 3 bytes, got 2"),
    ("2B", False, None, "truncated: 0x2B request needs 2 bytes, got 1"),
    ("2B 0E 05 00", False, None, "read device id code 5 outside 1..4"),
    ("2B 0E 01", False, None, "truncated: 0x2B request needs 4 bytes, got 3"),
    ("2B 0E 01 01 00 00 02 00 01 41", True, None, "1 objects but number of objects 2"),
    (
        "2B 0E 01 01 00 00 01 00 05 41",
        True,
        None,
        "object 1 truncated; 0 objects but number of objects 1",
    ),
    ("2B 0E 01 01 01 00 00", True, None, "more follows 0x01 is not 0x00/0xFF"),
    ("2B 0E 01 01 00", True, None, "truncated: 0x2B response needs 7 bytes, got 5"),
]


@pytest.mark.parametrize(("text", "response", "req", "reason"), CASES)
def test_reason(text: str, response: bool, req: str | None, reason: str) -> None:
    paired = decode_pdu(h(req), False) if req else None
    if paired is not None:
        assert paired.malformed is None, paired.malformed
    pdu = decode_pdu(h(text), response, paired)
    assert pdu.malformed == reason
    assert pdu.raw == h(text)


def test_decoded_as_far_as_possible() -> None:
    pdu = decode_pdu(h("03 00 6B 00"), False)
    assert (pdu.address, pdu.count) == (107, None)
    pdu = decode_pdu(h("03 06 00 01 00 02"), True)
    assert pdu.byte_count == 6 and pdu.values == (1, 2)
    pdu = decode_pdu(h("05 00 AC 12 34"), False)
    assert pdu.address == 172 and pdu.values is None
    assert pdu.fields["raw_value"] == 0x1234
    pdu = decode_pdu(h("01 02 13 00"), True, decode_pdu(h("01 01 2C 00 05"), False))
    assert pdu.values == (1, 1, 0, 0, 1)  # still trimmed: the bytes hold 5 bits
    pdu = decode_pdu(h("02 01 13"), True, decode_pdu(h("02 01 2C 00 09"), False))
    assert pdu.values == (1, 1, 0, 0, 1, 0, 0, 0)  # too few bits to trim: all kept
    pdu = decode_pdu(h("83 02"), False)
    assert pdu.fc == 0x03 and pdu.kind is Kind.REQUEST and pdu.fields["data"] == b"\x02"
    pdu = decode_pdu(b"", True)
    assert pdu.fc == 0 and pdu.kind is Kind.RESPONSE and pdu.raw == b""


def test_several_reasons_joined() -> None:
    pdu = decode_pdu(h("10 FF FF 00 7C 02 00 01 00"), False)
    assert pdu.malformed == (
        "byte count 2 but 3 data bytes; count 124 outside 1..123; "
        "address 65535 + count 124 exceeds 65536; byte count 2 but 124 registers need 248"
    )


def test_limits_exact() -> None:
    """The spec maxima pass, one more is flagged."""
    for fc, top in ((0x01, 2000), (0x02, 2000), (0x03, 125), (0x04, 125)):
        assert decode_pdu(encode_read_request(fc, 0, top), False).malformed is None
        assert decode_pdu(encode_read_request(fc, 0, 1), False).malformed is None
        flagged = decode_pdu(encode_read_request(fc, 0, top + 1), False).malformed
        assert flagged == f"count {top + 1} outside 1..{top}"
    ok = decode_pdu(encode_write_multiple_request(0x0F, 0, [1] * 1968), False)
    assert ok.malformed is None and ok.byte_count == 246
    bad = decode_pdu(encode_write_multiple_request(0x0F, 0, [1] * 1969), False)
    assert bad.malformed == "count 1969 outside 1..1968"
    ok = decode_pdu(encode_write_multiple_request(0x10, 0, [7] * 123), False)
    assert ok.malformed is None and ok.values == (7,) * 123
    bad = decode_pdu(encode_write_multiple_request(0x10, 0, [7] * 124), False)
    assert bad.malformed == "count 124 outside 1..123"
    write = b"\x00\x00\x00\x79\xf2" + b"\x00\x01" * 121
    assert decode_pdu(b"\x17\x00\x00\x00\x7d" + write, False).malformed is None
    write = b"\x00\x00\x00\x7a\xf4" + b"\x00\x01" * 122
    bad = decode_pdu(b"\x17\x00\x00\x00\x7d" + write, False)
    assert bad.malformed == "write count 122 outside 1..121"
    assert decode_pdu(encode_read_request(0x03, 0xFFFF, 1), False).malformed is None


def test_request_context_ignored_when_not_a_pair() -> None:
    other = decode_pdu(h("02 01 2C 00 05"), False)
    pdu = decode_pdu(h("01 01 13"), True, other)  # different function code
    assert pdu.malformed is None and pdu.values == (1, 1, 0, 0, 1, 0, 0, 0)
    answer = decode_pdu(h("01 01 13"), True)
    pdu = decode_pdu(h("01 01 13"), True, answer)  # a response is no request
    assert pdu.values == (1, 1, 0, 0, 1, 0, 0, 0)


def test_read_file_record_response_with_byte_count_0_is_malformed() -> None:
    # the request and both 0x15 frames were flagged, this was not
    from mbmon.protocol.pdu import decode_pdu

    pdu = decode_pdu(bytes([0x14, 0x00]), True)
    assert pdu.malformed == "byte count 0"
    assert decode_pdu(bytes([0x14, 0x00]), False).malformed is not None
    ok = decode_pdu(bytes([0x14, 0x04, 0x03, 0x06, 0x00, 0x2A]), True)
    assert ok.malformed is None
