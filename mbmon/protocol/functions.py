"""The one function-code table: what each public Modbus function code is.

Every layer that needs to know something about a function code reads it here
(one function-code table drives pdu, pairing, formatting and
annotation):

* :mod:`mbmon.protocol.pdu` -- names (``FUNCTION_NAMES``), PDU lengths for RTU
  framing and MBAP resync (:func:`~mbmon.protocol.pdu.pdu_length`), the data
  table of a code (:func:`~mbmon.protocol.pdu.table_of`); its field decoders
  (:mod:`mbmon.protocol.fields_access` by shape, :mod:`mbmon.protocol.fields_device`
  by code) are picked by this table;
* :mod:`mbmon.protocol.pairing` -- which responses are decoded again with their
  request (:data:`PAIR_ALWAYS`, :data:`PAIR_ON_COUNT`);
* :mod:`mbmon.format` -- names, bit or register values, reads whose response
  takes its address from the request;
* :mod:`mbmon.semantics.annotate` -- the profile table a code addresses
  (:data:`PROFILE_TABLE`);
* the proxy's guard (:mod:`mbmon.proxy.guard`) -- what writes and where
  (``writes``, ``table``, ``shape``), what is known to only read (``read``,
  ``only_reads``) and where a sub-function sits (``sub_bytes``).

A new function code is one :class:`FunctionCode` entry here -- or one
:func:`register` call for a user-defined code -- plus its field decoder in
``protocol/fields_device.py`` only when its fields have a layout of their own
(no ``shape``).
Quantity limits, the data table, read/write nature and the mask-write rule live
here only; modules that copy something out of the table do it in a
:func:`derived` function, so that a registered code reaches them too. Pure data
and small pure functions: imports nothing from mbmon but the model.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final

from mbmon.model import Kind, Pdu

__all__ = [
    "FUNCTIONS",
    "MAX_READ_WORDS",
    "NEED_MORE",
    "PAIR_ALWAYS",
    "PAIR_ON_COUNT",
    "PROFILE_TABLE",
    "SHAPE",
    "SHAPES",
    "SHIPPED",
    "FunctionCode",
    "LengthRule",
    "WriteSpan",
    "derived",
    "is_write",
    "mask_write",
    "register",
    "unregister",
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

    ``shape`` is the layout of its fields, which picks the field decoder in
    ``protocol/fields_access.py`` and says how every layer reads it (:data:`SHAPES`): ``"read"``
    (address + count, answered by a byte count and values), ``"write_single"``
    (address + one value, echoed), ``"write_multiple"`` (address + count + byte
    count + values, answered by address + count), ``"mask_write"``,
    ``"read_write"`` (0x17), or ``None`` (a layout of its own, decoded by its
    code). ``max_count`` is the spec's quantity limit of its count (the read
    part of 0x17), ``max_write_count`` that of 0x17's write part.

    ``only_reads`` says a request of it never changes server data when that is not
    already plain (a ``read`` that does not write is a read): ``True`` for every
    request, or the sub-functions that only read. ``sub_bytes`` is how many bytes
    after the code name a sub-function (0x08: 2; 0x2B: 1, its MEI type).
    """

    code: int
    name: str
    request_length: LengthRule
    response_length: LengthRule
    table: str | None = None
    writes: bool = False
    bits: bool = False
    read: bool = False
    shape: str | None = None
    max_count: int | None = None
    max_write_count: int | None = None
    only_reads: bool | frozenset[int] = False
    sub_bytes: int = 0


#: The field layouts a :class:`FunctionCode` may name as its ``shape``.
SHAPES: Final = frozenset({"read", "write_single", "write_multiple", "mask_write", "read_write"})

_READ_BITS: Final = 2000  # the spec's quantity limits
_READ_WORDS: Final = 125
_WRITE_BITS: Final = 1968
_WRITE_WORDS: Final = 123
_RW_WRITE_WORDS: Final = 121
MAX_READ_WORDS: Final = _READ_WORDS
#: Diagnostics (0x08) sub-functions that only read: Return Query Data, the
#: diagnostic register and the counters (0x0B-0x12).
_DIAGNOSTIC_READS: Final = frozenset({0x00, 0x02, *range(0x0B, 0x13)})
"""Most registers one read may ask for (the spec's limit for 0x03/0x04): the widest
field a device profile may declare."""

FUNCTIONS: Final[dict[int, FunctionCode]] = {
    f.code: f
    for f in (
        FunctionCode(
            0x01, "Read Coils", 5, (1, 2), "coil", bits=True, read=True,
            shape="read", max_count=_READ_BITS,
        ),
        FunctionCode(
            0x02, "Read Discrete Inputs", 5, (1, 2), "discrete_input", bits=True, read=True,
            shape="read", max_count=_READ_BITS,
        ),
        FunctionCode(
            0x03, "Read Holding Registers", 5, (1, 2), "holding_register", read=True,
            shape="read", max_count=_READ_WORDS,
        ),
        FunctionCode(
            0x04, "Read Input Registers", 5, (1, 2), "input_register", read=True,
            shape="read", max_count=_READ_WORDS,
        ),
        FunctionCode(
            0x05, "Write Single Coil", 5, 5, "coil", writes=True, bits=True,
            shape="write_single",
        ),
        FunctionCode(
            0x06, "Write Single Register", 5, 5, "holding_register", writes=True,
            shape="write_single",
        ),
        FunctionCode(0x07, "Read Exception Status", 1, 2, only_reads=True),
        FunctionCode(
            0x08, "Diagnostics", _diag_request, _diag_response, sub_bytes=2,
            only_reads=_DIAGNOSTIC_READS,
        ),
        FunctionCode(0x0B, "Get Comm Event Counter", 1, 5, only_reads=True),
        FunctionCode(0x0C, "Get Comm Event Log", 1, (1, 2), only_reads=True),
        FunctionCode(
            0x0F, "Write Multiple Coils", (5, 6), 5, "coil", writes=True, bits=True,
            shape="write_multiple", max_count=_WRITE_BITS,
        ),
        FunctionCode(
            0x10, "Write Multiple Registers", (5, 6), 5, "holding_register", writes=True,
            shape="write_multiple", max_count=_WRITE_WORDS,
        ),
        FunctionCode(0x11, "Report Server ID", 1, (1, 2), only_reads=True),
        FunctionCode(0x14, "Read File Record", (1, 2), (1, 2), only_reads=True),
        FunctionCode(0x15, "Write File Record", (1, 2), (1, 2), writes=True),
        FunctionCode(
            0x16, "Mask Write Register", 7, 7, "holding_register", writes=True,
            shape="mask_write",
        ),
        FunctionCode(
            0x17, "Read/Write Multiple Registers", (9, 10), (1, 2), "holding_register",
            writes=True, read=True, shape="read_write",
            max_count=_READ_WORDS, max_write_count=_RW_WRITE_WORDS,
        ),
        FunctionCode(0x18, "Read FIFO Queue", 3, _fifo_response, only_reads=True),
        FunctionCode(
            0x2B, "Encapsulated Interface Transport", _mei_request, None, sub_bytes=1,
            only_reads=frozenset({0x0E}),  # Read Device Identification
        ),
    )
}  # fmt: skip

#: The rows as shipped, whatever :func:`register` adds or replaces later.
SHIPPED: Final[Mapping[int, FunctionCode]] = MappingProxyType(dict(FUNCTIONS))

#: Function code -> its :attr:`FunctionCode.shape` (codes with a shape only).
SHAPE: Final[dict[int, str]] = {}
#: Responses decoded again with their request, always: bit reads are trimmed to the
#: requested count, diagnostics and file records copy or compare request fields.
PAIR_ALWAYS: Final[set[int]] = set()
#: Responses decoded again with their request when the byte count disagrees with
#: the requested register count (register reads are only checked against it).
PAIR_ON_COUNT: Final[set[int]] = set()
_PAIR_BY_FIELDS: Final = (0x08, 0x14)  # their decoders compare request fields

_rebuilds: list[Callable[[], None]] = []


def derived(rebuild: Callable[[], None]) -> Callable[[], None]:
    """Register ``rebuild``, which (re)computes a module's tables derived from
    :data:`FUNCTIONS` in place, and run it now; :func:`register` runs it again.
    A module that copies anything out of the table does it in such a function."""
    _rebuilds.append(rebuild)
    rebuild()
    return rebuild


def register(spec: FunctionCode) -> None:
    """Add (or replace) one function code -- a user-defined one such as 0x41 --
    and bring every table derived from :data:`FUNCTIONS` up to date. A code with a
    ``shape`` is decoded, paired, annotated and printed like the public codes of
    that shape; without one its bytes after the code stay in ``fields["data"]``."""
    if not 0 < spec.code < 0x80:
        raise ValueError(f"function code {spec.code} is outside 1..127")
    if spec.shape is not None and spec.shape not in SHAPES:
        raise ValueError(f"unknown shape {spec.shape!r} (one of {', '.join(sorted(SHAPES))})")
    if spec.bits and spec.shape in ("mask_write", "read_write"):
        raise ValueError(f"shape {spec.shape!r} is for registers, not bits")
    FUNCTIONS[spec.code] = spec
    _rebuild_all()


def unregister(code: int) -> None:
    """Remove one function code added by :func:`register` (tests, plug-ins)."""
    FUNCTIONS.pop(code, None)
    _rebuild_all()


def _rebuild_all() -> None:
    for rebuild in _rebuilds:
        rebuild()


@derived
def _own_tables() -> None:
    SHAPE.clear()
    SHAPE.update({c: f.shape for c, f in FUNCTIONS.items() if f.shape is not None})
    PAIR_ALWAYS.clear()
    PAIR_ALWAYS.update(c for c, f in FUNCTIONS.items() if f.read and f.bits)
    PAIR_ALWAYS.update(_PAIR_BY_FIELDS)
    PAIR_ON_COUNT.clear()
    PAIR_ON_COUNT.update(c for c, f in FUNCTIONS.items() if f.read and not f.bits)


def mask_write(current: int, and_mask: int, or_mask: int) -> int:
    """The register a Mask Write (0x16) leaves: ``(current AND and_mask) OR
    (or_mask AND NOT and_mask)`` (Modbus Application Protocol 6.16)."""
    return (current & and_mask) | (or_mask & ~and_mask & 0xFFFF)


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
    spec = FUNCTIONS[fc]
    if spec.table is None:  # 0x15: file records (its own layout)
        return tuple(
            WriteSpan("file", rec["record_number"], rec["record_length"], rec["file_number"])
            for rec in pdu.fields.get("records", ())
        )
    if spec.shape == "read_write":
        address, count = pdu.fields.get("write_address"), pdu.fields.get("write_count")
    else:
        address = pdu.address
        count = pdu.count if pdu.count is not None else 1  # mask write: one register
    if address is None or count is None:
        return ()
    table = "coil" if spec.table == "coil" else "hr"
    return (WriteSpan(table, address, count),)
