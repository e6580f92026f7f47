"""Properties: decode_pdu/pdu_length never raise and agree; encoders round-trip."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.model import Kind
from mbmon.protocol.pdu import (
    NEED_MORE,
    decode_pdu,
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
    pdu_length,
)

KNOWN = [0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0B, 0x0C, 0x0F, 0x10, 0x11, 0x14]
KNOWN += [0x15, 0x16, 0x17, 0x18, 0x2B]
FIRST = st.one_of(
    st.sampled_from(KNOWN),
    st.sampled_from(KNOWN).map(lambda fc: fc | 0x80),
    st.integers(0, 255),
)
PDUS = st.builds(lambda fc, rest: bytes((fc,)) + rest, FIRST, st.binary(max_size=40))
ANY = st.one_of(st.binary(max_size=40), PDUS)
FRAMING = ("truncated:", "trailing", " data bytes")

settings.register_profile("pdu", max_examples=300, deadline=None)
settings.load_profile("pdu")


@given(ANY, st.booleans(), st.one_of(st.none(), ANY))
def test_decode_never_raises(data: bytes, response: bool, req: bytes | None) -> None:
    request = decode_pdu(req, False) if req is not None else None
    for buf in (data, bytearray(data), memoryview(data)):
        pdu = decode_pdu(buf, response, request)
        assert pdu.raw == data
        assert pdu.fc == (data[0] & 0x7F if data else 0)
        if pdu.malformed is not None:
            assert "internal" not in pdu.malformed
            assert pdu.malformed == pdu.malformed.strip() and not pdu.malformed[0].isupper()
        if response and data and data[0] & 0x80:
            assert pdu.kind is Kind.EXCEPTION
        else:
            assert pdu.kind is (Kind.RESPONSE if response else Kind.REQUEST)


@given(ANY, st.booleans())
def test_length_agrees_with_decoder(data: bytes, response: bool) -> None:
    """Where pdu_length commits to a length, the decoder finds exactly that PDU."""
    n = pdu_length(data, response)
    assert n is None or n == NEED_MORE or n >= 1
    if n is None or n == NEED_MORE:
        return
    if len(data) >= n:
        reason = decode_pdu(data[:n], response).malformed or ""
        assert not any(f in reason for f in FRAMING), reason
    else:
        assert decode_pdu(data, response).malformed is not None
    for cut in range(len(data)):  # a longer prefix never changes a committed length
        shorter = pdu_length(data[:cut], response)
        assert shorter in (NEED_MORE, n), cut


U16 = st.integers(0, 0xFFFF)


@given(st.sampled_from([1, 2, 3, 4]), U16, U16)
def test_read_request_round_trip(fc: int, address: int, count: int) -> None:
    pdu = decode_pdu(encode_read_request(fc, address, count), False)
    assert (pdu.fc, pdu.address, pdu.count) == (fc, address, count)
    assert pdu_length(pdu.raw, False) == 5


@given(st.sampled_from([1, 2]), st.lists(st.integers(0, 1), min_size=1, max_size=2000))
def test_read_bits_round_trip(fc: int, bits: list[int]) -> None:
    request = decode_pdu(encode_read_request(fc, 0, len(bits)), False)
    raw = encode_read_response(fc, bits)
    pdu = decode_pdu(raw, True, request)
    assert pdu.malformed is None
    assert pdu.values == tuple(bits) and pdu.byte_count == (len(bits) + 7) // 8
    assert pdu_length(raw, True) == len(raw)


@given(st.sampled_from([3, 4]), st.lists(U16, min_size=1, max_size=125))
def test_read_registers_round_trip(fc: int, regs: list[int]) -> None:
    request = decode_pdu(encode_read_request(fc, 7, len(regs)), False)
    raw = encode_read_response(fc, regs)
    pdu = decode_pdu(raw, True, request)
    assert pdu.malformed is None and pdu.values == tuple(regs)
    assert pdu_length(raw, True) == len(raw)


@given(U16, st.one_of(st.booleans(), U16))
def test_write_single_round_trip(address: int, value: bool | int) -> None:
    raw = encode_write_single(0x05, address, value) if isinstance(value, bool) else b""
    if raw:
        pdu = decode_pdu(raw, True)
        assert pdu.address == address and pdu.values == (int(value),) and pdu.malformed is None
    else:
        pdu = decode_pdu(encode_write_single(0x05, address, value), False)
        assert pdu.address == address
        if value in (0, 0xFF00):
            assert pdu.values == ((1,) if value else (0,)) and pdu.malformed is None
        else:
            assert pdu.values is None and pdu.fields["raw_value"] == value
        pdu = decode_pdu(encode_write_single(0x06, address, int(value)), False)
        assert (pdu.address, pdu.count, pdu.values) == (address, 1, (value,))


@given(U16, st.lists(st.integers(0, 1), min_size=1, max_size=1968))
def test_write_coils_round_trip(address: int, bits: list[int]) -> None:
    raw = encode_write_multiple_request(0x0F, address, bits)
    pdu = decode_pdu(raw, False)
    assert (pdu.address, pdu.count, pdu.values) == (address, len(bits), tuple(bits))
    assert pdu.malformed is None or "exceeds 65536" in pdu.malformed
    assert pdu_length(raw, False) == len(raw)
    resp = decode_pdu(encode_write_multiple_response(0x0F, address, len(bits)), True)
    assert (resp.address, resp.count) == (address, len(bits))


@given(U16, st.lists(U16, min_size=1, max_size=123))
def test_write_registers_round_trip(address: int, regs: list[int]) -> None:
    raw = encode_write_multiple_request(0x10, address, regs)
    pdu = decode_pdu(raw, False)
    assert (pdu.address, pdu.count, pdu.values) == (address, len(regs), tuple(regs))
    assert pdu.byte_count == 2 * len(regs)
    assert pdu_length(raw, False) == len(raw)
    resp = decode_pdu(encode_write_multiple_response(0x10, address, len(regs)), True)
    assert (resp.address, resp.count, resp.kind) == (address, len(regs), Kind.RESPONSE)


@given(st.integers(1, 0x7F), st.integers(0, 255))
def test_exception_round_trip(fc: int, code: int) -> None:
    pdu = decode_pdu(encode_exception(fc, code), True)
    assert (pdu.kind, pdu.fc, pdu.exception_code, pdu.malformed) == (
        Kind.EXCEPTION,
        fc,
        code,
        None,
    )


def test_encoders_match_spec_bytes() -> None:
    assert encode_read_request(0x03, 0x6B, 3) == bytes.fromhex("03006B0003")
    assert encode_read_response(
        0x01, [1, 0, 1, 1, 0, 0, 1, 1, 1, 1, 0, 1, 0, 1, 1, 0, 1, 0, 1]
    ) == (bytes.fromhex("0103CD6B05"))
    assert encode_read_response(0x02, [1, 1, 0, 0, 1, 1, 1], count=5) == bytes.fromhex("020113")
    assert encode_read_response(0x03, [555, 0, 100]) == bytes.fromhex("0306022B00000064")
    assert encode_write_single(0x05, 172, True) == bytes.fromhex("0500ACFF00")
    assert encode_write_single(0x05, 172, False) == bytes.fromhex("0500AC0000")
    assert encode_write_single(0x05, 172, 0x1234) == bytes.fromhex("0500AC1234")
    assert encode_write_single(0x06, 1, 3) == bytes.fromhex("0600010003")
    assert encode_write_multiple_request(0x0F, 19, [1, 0, 1, 1, 0, 0, 1, 1, 1, 0]) == (
        bytes.fromhex("0F0013000A02CD01")
    )
    assert encode_write_multiple_request(0x10, 201, [111, 222, 333]) == (
        bytes.fromhex("1000C9000306006F00DE014D")
    )
    assert encode_write_multiple_response(0x10, 1, 2) == bytes.fromhex("1000010002")
    assert encode_exception(0x03, 2) == bytes.fromhex("8302")


@pytest.mark.parametrize(
    "call",
    [
        lambda: encode_read_request(0x03, 0x10000, 1),
        lambda: encode_read_request(0x03, 0, -1),
        lambda: encode_read_response(0x05, [1]),
        lambda: encode_read_response(0x01, [1], count=2),
        lambda: encode_read_response(0x03, [0x10000]),
        lambda: encode_write_single(0x03, 0, 1),
        lambda: encode_write_multiple_request(0x06, 0, [1]),
        lambda: encode_write_multiple_request(0x10, 0, [1] * 128),  # byte count > 255
        lambda: encode_write_multiple_response(0x03, 0, 1),
        lambda: encode_exception(0x03, 256),
    ],
)
def test_encoders_reject(call: object) -> None:
    with pytest.raises(ValueError):
        call()  # type: ignore[operator]
