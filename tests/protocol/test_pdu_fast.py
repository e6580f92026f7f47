"""The fast paths of PDU decoding and RTU length prediction give the general answers.

``pdu._well_formed`` decides the frequent PDUs (01-06, 0F, 10) that break no
rule without the field decoders' collector; wherever it answers, its Pdu must
be the one the field decoders make (``pdu._decode_general``), and it must
answer for the usual well-formed PDUs (else it is dead code).
``pdu.simple_length_rules`` (inlined by the RTU framer) must give
``pdu_length``'s answers.
"""

from __future__ import annotations

import struct

from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.protocol.pdu import (
    NEED_MORE,
    _decode_general,
    _well_formed,
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
    pdu_length,
    simple_length_rules,
)

FAST = (0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F, 0x10)
WORD = st.integers(0, 0xFFFF)


def _near_valid(fc: int, a: int, count: int, tail: bytes, bc_delta: int) -> bytes:
    """A PDU shaped like a frequent one, often valid, often off by one somewhere."""
    head = bytes((fc,)) + struct.pack(">HH", a, count)
    if fc in (0x0F, 0x10):
        bc = ((count + 7) // 8 if fc == 0x0F else 2 * count) + bc_delta
        return head + bytes((bc & 0xFF,)) + tail[: max(bc, 0)]
    return head


PDUS = st.one_of(
    st.builds(lambda fc, rest: bytes((fc,)) + rest, st.sampled_from(FAST), st.binary(max_size=40)),
    st.builds(
        _near_valid,
        st.sampled_from(FAST),
        WORD,
        st.one_of(st.integers(0, 130), st.integers(1960, 2001), WORD),
        st.binary(min_size=250, max_size=250),
        st.sampled_from((0, 0, 0, 1, -1)),
    ),
    st.builds(
        lambda fc, bc, rest: bytes((fc, bc)) + rest[:bc],
        st.sampled_from((0x01, 0x02, 0x03, 0x04)),
        st.integers(0, 255),
        st.binary(min_size=255, max_size=255),
    ),
)


@settings(max_examples=1500, deadline=None)
@given(PDUS, st.booleans())
def test_well_formed_fast_path_is_the_general_decoder(data: bytes, response: bool) -> None:
    fast = _well_formed(data, data[0], response)
    general = _decode_general(data, data[0], response, None)
    if fast is not None:
        assert fast == general
        assert general.malformed is None
    assert type(general.values) in (tuple, type(None))


def test_well_formed_answers_the_usual_pdus() -> None:
    usual = [
        (encode_read_request(0x03, 100, 10), False),
        (encode_read_request(0x01, 0, 2000), False),
        (encode_read_response(0x03, [1, 2, 3]), True),
        (encode_read_response(0x02, [1, 0, 1], count=3), True),
        (encode_write_single(0x05, 7, True), False),
        (encode_write_single(0x05, 7, False), True),
        (encode_write_single(0x06, 7, 0xBEEF), True),
        (encode_write_multiple_request(0x0F, 3, [1, 0, 1, 1, 0, 0, 1, 0, 1]), False),
        (encode_write_multiple_request(0x10, 3, [1, 2, 0xFFFF]), False),
        (encode_write_multiple_response(0x10, 3, 3), True),
        (encode_write_multiple_response(0x0F, 3, 1968), True),
    ]
    for pdu, response in usual:
        fast = _well_formed(pdu, pdu[0], response)
        assert fast is not None, pdu.hex()
        assert fast == _decode_general(pdu, pdu[0], response, None)


@given(st.binary(min_size=1, max_size=20), st.booleans())
def test_simple_length_rules_agree_with_pdu_length(data: bytes, response: bool) -> None:
    rule = simple_length_rules(response).get(data[0])
    if rule is None:
        return
    if type(rule) is int:
        assert pdu_length(data, response) == rule
    else:
        index, base = rule
        want = NEED_MORE if len(data) <= index else base + data[index]
        assert pdu_length(data, response) == want
