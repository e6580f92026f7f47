"""The one function-code table: what each public Modbus function code is.

Every layer that needs to know something about a function code reads it here
(one function-code table drives pdu, pairing, formatting and
annotation):

* :mod:`mbmon.protocol.pdu` -- names (``FUNCTION_NAMES``), PDU lengths for RTU
  framing and MBAP resync (:func:`~mbmon.protocol.pdu.pdu_length`), the data
  table of a code (:func:`~mbmon.protocol.pdu.table_of`); its field decoders
  stay in ``pdu._DECODERS`` (checked against this table);
* :mod:`mbmon.protocol.pairing` -- which responses are decoded again with their
  request (:data:`PAIR_ALWAYS`, :data:`PAIR_ON_COUNT`);
* :mod:`mbmon.format` -- names, bit or register values, reads whose response
  takes its address from the request;
* :mod:`mbmon.semantics.annotate` -- the profile table a code addresses
  (:data:`PROFILE_TABLE`);
* the proxy's write guard -- :func:`is_write` and :func:`write_spans`.

A new function code is one :class:`FunctionCode` entry here (plus its field
decoder in ``pdu.py`` when it has fields). Pure data and small pure functions:
imports nothing from mbmon but the model.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

from mbmon.model import Kind, Pdu

__all__ = [
    "FUNCTIONS",
    "NEED_MORE",
    "PAIR_ALWAYS",
    "PAIR_ON_COUNT",
    "PROFILE_TABLE",
    "FunctionCode",
    "LengthRule",
    "WriteSpan",
    "is_write",
    "write_spans",
]

NEED_MORE: Final = -1
"""A length rule's result: more bytes are needed before the length is known."""

#: How long a PDU is: an int (fixed), ``(i, base)`` (``base + data[i]``), a function of
#: the PDU's first bytes (returning a length, :data:`NEED_MORE` or ``None``), or
#: ``None`` (unpredictable: only a CRC scan finds the end).
LengthRule = int | tuple[int, int] | Callable[[bytes | bytearray | memoryview], int | None] | None


def _diagnostics_length(data: bytes | bytearray | memoryview, response: bool) -> int | None:
    # sub-function 0x00 echoes any number of bytes, 0x15 replies carry Modbus Plus
    # statistics; every other sub-function is 5 bytes
    if len(data) < 3:
        return NEED_MORE
    sub = (data[1] << 8) | data[2]
    if sub == 0x00 or (sub == 0x15 and response):
        return None
    return 5


def _diag_request(data: bytes | bytearray | memoryview) -> int | None:
    return _diagnostics_length(data, False)


def _diag_response(data: bytes | bytearray | memoryview) -> int | None:
    return _diagnostics_length(data, True)


def _fifo_response(data: bytes | bytearray | memoryview) -> int | None:
    return NEED_MORE if len(data) < 3 else 3 + ((data[1] << 8) | data[2])


def _mei_request(data: bytes | bytearray | memoryview) -> int | None:
    if len(data) < 2:
        return NEED_MORE
    return 4 if data[1] == 0x0E else None


@dataclass(frozen=True, slots=True)
class FunctionCode:
    """One public function code.

    ``table`` is the data table it addresses (``"coil"``, ``"discrete_input"``,
    ``"holding_register"``, ``"input_register"``) or ``None``; ``writes`` whether
    its request changes server data (0x17 writes and reads); ``bits`` whether
    its values are bits; ``read`` whether it is a read whose response takes its
    address and count from the request.
    """

    code: int
    name: str
    request_length: LengthRule
    response_length: LengthRule
    table: str | None = None
    writes: bool = False
    bits: bool = False
    read: bool = False


FUNCTIONS: Final[dict[int, FunctionCode]] = {
    f.code: f
    for f in (
        FunctionCode(0x01, "Read Coils", 5, (1, 2), "coil", bits=True, read=True),
        FunctionCode(
            0x02, "Read Discrete Inputs", 5, (1, 2), "discrete_input", bits=True, read=True
        ),
        FunctionCode(0x03, "Read Holding Registers", 5, (1, 2), "holding_register", read=True),
        FunctionCode(0x04, "Read Input Registers", 5, (1, 2), "input_register", read=True),
        FunctionCode(0x05, "Write Single Coil", 5, 5, "coil", writes=True, bits=True),
        FunctionCode(0x06, "Write Single Register", 5, 5, "holding_register", writes=True),
        FunctionCode(0x07, "Read Exception Status", 1, 2),
        FunctionCode(0x08, "Diagnostics", _diag_request, _diag_response),
        FunctionCode(0x0B, "Get Comm Event Counter", 1, 5),
        FunctionCode(0x0C, "Get Comm Event Log", 1, (1, 2)),
        FunctionCode(0x0F, "Write Multiple Coils", (5, 6), 5, "coil", writes=True, bits=True),
        FunctionCode(0x10, "Write Multiple Registers", (5, 6), 5, "holding_register", writes=True),
        FunctionCode(0x11, "Report Server ID", 1, (1, 2)),
        FunctionCode(0x14, "Read File Record", (1, 2), (1, 2)),
        FunctionCode(0x15, "Write File Record", (1, 2), (1, 2), writes=True),
        FunctionCode(0x16, "Mask Write Register", 7, 7, "holding_register", writes=True),
        FunctionCode(
            0x17,
            "Read/Write Multiple Registers",
            (9, 10),
            (1, 2),
            "holding_register",
            writes=True,
            read=True,
        ),
        FunctionCode(0x18, "Read FIFO Queue", 3, _fifo_response),
        FunctionCode(0x2B, "Encapsulated Interface Transport", _mei_request, None),
    )
}

#: Responses decoded again with their request, always: bit reads are trimmed to the
#: requested count, diagnostics and file records copy or compare request fields.
PAIR_ALWAYS: Final = frozenset({0x01, 0x02, 0x08, 0x14})
#: Responses decoded again with their request when the byte count disagrees with
#: the requested register count (register reads are only checked against it).
PAIR_ON_COUNT: Final = frozenset({0x03, 0x04, 0x17})

#: Data table of :attr:`FunctionCode.table` -> profile table name (``semantics``).
PROFILE_TABLE: Final[dict[str, str]] = {
    "coil": "coils",
    "discrete_input": "discrete_inputs",
    "holding_register": "holding_registers",
    "input_register": "input_registers",
}


@dataclass(frozen=True, slots=True)
class WriteSpan:
    """What one write request touches: ``count`` items of ``table`` from ``address``.

    ``table`` is ``"coil"``, ``"hr"`` (holding registers) or ``"file"`` (0x15:
    ``address`` = record number, ``count`` = record length in words, ``file`` =
    file number).
    """

    table: str
    address: int
    count: int
    file: int | None = None


def is_write(pdu: Pdu) -> bool:
    """Whether ``pdu`` is a request that changes server data (05 06 0F 10 15 16 17)."""
    if pdu.kind is not Kind.REQUEST:
        return False
    spec = FUNCTIONS.get(pdu.fc)
    return spec is not None and spec.writes and not pdu.raw[0] & 0x80


def write_spans(pdu: Pdu) -> tuple[WriteSpan, ...]:
    """The data a write request touches (empty for other PDUs, or when the request
    is too damaged to tell its address): the proxy's write guard reads this.

    05/0F: coils from ``address``; 06/10/16: holding registers; 17: its write part
    (``write_address``/``write_count``); 15: one span per file sub-request.
    """
    if not is_write(pdu):
        return ()
    fc = pdu.fc
    if fc == 0x15:
        return tuple(
            WriteSpan("file", rec["record_number"], rec["record_length"], rec["file_number"])
            for rec in pdu.fields.get("records", ())
        )
    if fc == 0x17:
        address, count = pdu.fields.get("write_address"), pdu.fields.get("write_count")
    else:
        address = pdu.address
        count = pdu.count if pdu.count is not None else 1  # 0x16: one register
    if address is None or count is None:
        return ()
    table = "coil" if FUNCTIONS[fc].table == "coil" else "hr"
    return (WriteSpan(table, address, count),)
