"""PDU lengths predicted from the first bytes (RTU framing, MBAP resync).

Owns :func:`pdu_length`, :func:`simple_length_rules` (its function-free rules,
for a framer that inlines the common case) and the spec's quantity limits by
function code (``MAX_COUNT``, read by the field decoders), all copied out of
the one function-code table by :func:`_from_table`. Pure.
"""

from __future__ import annotations

from typing import Final

from mbmon.protocol.functions import FUNCTIONS, NEED_MORE, LengthRule, derived

__all__ = ["MAX_COUNT", "NEED_MORE", "pdu_length", "simple_length_rules"]


# Length rules by code, from the one table: int = fixed; (i, base) = base + data[i];
# a function of the first bytes for the codes whose length depends on a sub-code.
_REQ_LEN: Final[dict[int, LengthRule]] = {}  # by :func:`_from_table`
_RESP_LEN: Final[dict[int, LengthRule]] = {}
#: Function code -> the spec's quantity limit of its count (by :func:`_from_table`).
MAX_COUNT: Final[dict[int, int]] = {}


def pdu_length(data: bytes | bytearray | memoryview, response: bool) -> int | None:
    """Full PDU length (function code + data) predicted from its first bytes.

    Returns :data:`NEED_MORE` when the bytes present cannot tell yet (e.g. the
    byte-count byte has not arrived), ``None`` when the function code has no
    predictable length and only CRC scanning can find the end: unknown and
    user-defined codes, requests with the 0x80 bit, 0x2B responses and 0x2B
    requests other than MEI 0x0E, 0x08 sub-function 0x00 (Return Query Data
    echoes any number of bytes) and 0x08 sub-function 0x15 responses (Modbus
    Plus statistics). Every other 0x08 is 5 bytes. An exception response is 2.
    """
    n = len(data)
    if n == 0:
        return NEED_MORE
    fc = data[0]
    if fc & 0x80:
        return 2 if response else None
    spec = (_RESP_LEN if response else _REQ_LEN).get(fc)
    if spec is None:
        return None
    if type(spec) is int:
        return spec
    if type(spec) is tuple:
        index, base = spec
        return NEED_MORE if n <= index else base + data[index]
    return spec(data)  # type: ignore[operator]


def simple_length_rules(response: bool) -> dict[int, int | tuple[int, int]]:
    """The rules :func:`pdu_length` applies without a function, for a framer that
    inlines the common case: function code -> fixed PDU length (int) or
    ``(i, base)`` (length ``base + data[i]``, :data:`NEED_MORE` while ``data[i]``
    is missing). Responses include the exception codes 0x81..0xFF (2 bytes).
    Codes absent here go through :func:`pdu_length` (a function rule, or no
    predictable length). Same answers as :func:`pdu_length` by construction: it
    reads the same tables (tested)."""
    rules: dict[int, int | tuple[int, int]] = {
        code: rule
        for code, rule in (_RESP_LEN if response else _REQ_LEN).items()
        if type(rule) is int or type(rule) is tuple
    }
    if response:
        rules.update(dict.fromkeys(range(0x81, 0x100), 2))
    return rules


@derived
def _from_table() -> None:
    """Copy length rules and quantity limits out of the one table (again when a
    code is registered)."""
    for copy in (_REQ_LEN, _RESP_LEN, MAX_COUNT):
        copy.clear()
    for code, f in FUNCTIONS.items():
        if f.request_length is not None:
            _REQ_LEN[code] = f.request_length
        if f.response_length is not None:
            _RESP_LEN[code] = f.response_length
        if f.max_count is not None:
            MAX_COUNT[code] = f.max_count
