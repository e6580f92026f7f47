"""PDU by PDU: the core's own decode and generic note against the reference
(:func:`mbmon.protocol.pdu.decode_pdu`, the pairer's second decode with the request,
:func:`mbmon.format.generic_note`) on random and tabled bytes. Where the core says
``None`` it leaves the PDU to the reference; where it answers, it must agree."""

from __future__ import annotations

import pytest
from core_diff import require_core
from gen import every_function_pair
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon import core
from mbmon.format import generic_note
from mbmon.model import Kind
from mbmon.protocol.pairing import _needs_request
from mbmon.protocol.pdu import decode_pdu

_KIND = {Kind.REQUEST: "request", Kind.RESPONSE: "response", Kind.EXCEPTION: "exception"}


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def check(data: bytes, response: bool, request: bytes | None = None) -> bool:
    """Compare one PDU; True when the core decoded it itself."""
    got = core._pdu_entry(data, response, request)
    if got is None:
        return False
    req_pdu = decode_pdu(request, False) if request is not None else None
    pdu = decode_pdu(data, response)
    if req_pdu is not None and _needs_request(pdu, req_pdu):
        pdu = decode_pdu(data, True, request=req_pdu)
    assert pdu.malformed is None and not pdu.fields, "the core took a PDU with a report"
    address, count = pdu.address, pdu.count
    if address is None and req_pdu is not None and pdu.kind is not Kind.REQUEST:
        address, count = req_pdu.address, req_pdu.count  # as record_to_json
    values = list(pdu.values) if pdu.values is not None else None
    want = (pdu.fc, _KIND[pdu.kind], address, count, values, pdu.exception_code)
    assert got[:6] == want
    assert got[6] == generic_note(pdu, req_pdu)
    return True


def test_tabled_pairs() -> None:
    native = 0
    for req, resp in every_function_pair():
        native += check(req, False)
        native += check(resp, True)
        native += check(resp, True, req)
    assert native >= 25


@settings(max_examples=3000, deadline=None)
@given(
    fc=st.sampled_from([1, 2, 3, 4, 5, 6, 15, 16, 0x81, 0x83, 0x90, 0, 7, 0x41]),
    body=st.binary(max_size=12),
    response=st.booleans(),
)
def test_random_pdus(fc: int, body: bytes, response: bool) -> None:
    check(bytes([fc]) + body, response)


@settings(max_examples=3000, deadline=None)
@given(
    fc=st.sampled_from([1, 2, 3, 4]),
    address=st.integers(0, 0xFFFF),
    count=st.integers(0, 2100),
    body=st.binary(max_size=300),
    exc=st.booleans(),
)
def test_random_answers_with_requests(
    fc: int, address: int, count: int, body: bytes, exc: bool
) -> None:
    request = bytes([fc, address >> 8, address & 255, count >> 8, count & 255])
    n = len(body)
    answer = bytes([fc | (0x80 if exc else 0), n & 255]) + body  # byte counts right and wrong
    check(answer, True, request)
    check(answer[:2], True, request)
