"""Names of Modbus function codes, exception codes, diagnostics and MEI objects.

Owns the name tables the formatter prints and :func:`table_of` for annotators.
``FUNCTION_NAMES`` and the data tables are copied out of the one function-code
table (:mod:`mbmon.protocol.functions`) by :func:`_from_table`; the rest are the
spec's fixed lists. All are importable from :mod:`mbmon.protocol.pdu` too.
Pure data.
"""

from __future__ import annotations

from typing import Final

from mbmon.protocol.functions import FUNCTIONS, derived

__all__ = [
    "DIAGNOSTIC_NAMES",
    "EXCEPTION_NAMES",
    "FUNCTION_NAMES",
    "MEI_OBJECT_NAMES",
    "MEI_TYPE_NAMES",
    "NO_REPLY_DIAGNOSTICS",
    "READ_DEVICE_ID_NAMES",
    "table_of",
]

FUNCTION_NAMES: Final[dict[int, str]] = {}

EXCEPTION_NAMES: Final[dict[int, str]] = {
    0x01: "Illegal Function",
    0x02: "Illegal Data Address",
    0x03: "Illegal Data Value",
    0x04: "Server Device Failure",
    0x05: "Acknowledge",
    0x06: "Server Device Busy",
    0x08: "Memory Parity Error",
    0x0A: "Gateway Path Unavailable",
    0x0B: "Gateway Target Device Failed To Respond",
}

# Sub-functions of 0x08 defined by the spec; 0x05-0x09 and 0x13 are reserved.
DIAGNOSTIC_NAMES: Final[dict[int, str]] = {
    0x00: "Return Query Data",
    0x01: "Restart Communications Option",
    0x02: "Return Diagnostic Register",
    0x03: "Change ASCII Input Delimiter",
    0x04: "Force Listen Only Mode",
    0x0A: "Clear Counters and Diagnostic Register",
    0x0B: "Return Bus Message Count",
    0x0C: "Return Bus Communication Error Count",
    0x0D: "Return Bus Exception Error Count",
    0x0E: "Return Server Message Count",
    0x0F: "Return Server No Response Count",
    0x10: "Return Server NAK Count",
    0x11: "Return Server Busy Count",
    0x12: "Return Bus Character Overrun Count",
    0x14: "Clear Overrun Counter and Flag",
    0x15: "Get/Clear Modbus Plus Statistics",
}

#: Diagnostics sub-functions a server never answers (spec 6.8: "No response is
#: returned" to 04 Force Listen Only Mode): a request of one is not "No response".
NO_REPLY_DIAGNOSTICS: Final = frozenset({0x04})

#: Read Device ID codes of a Read Device Identification (MEI 0x0E) request.
READ_DEVICE_ID_NAMES: Final[dict[int, str]] = {
    0x01: "basic",
    0x02: "regular",
    0x03: "extended",
    0x04: "one object",
}

MEI_TYPE_NAMES: Final[dict[int, str]] = {
    0x0D: "CANopen General Reference",
    0x0E: "Read Device Identification",
}

MEI_OBJECT_NAMES: Final[dict[int, str]] = {
    0x00: "VendorName",
    0x01: "ProductCode",
    0x02: "MajorMinorRevision",
    0x03: "VendorUrl",
    0x04: "ProductName",
    0x05: "ModelName",
    0x06: "UserApplicationName",
}

_TABLES: Final[dict[int, str]] = {}  # by :func:`_from_table`


def table_of(fc: int) -> str | None:
    """The data table a function code addresses, or ``None`` when it addresses none.

    ``"coil"`` (01/05/0F), ``"discrete_input"`` (02), ``"holding_register"``
    (03/06/10/16/17) or ``"input_register"`` (04); the exception bit is ignored.
    """
    return _TABLES.get(fc & 0x7F)


@derived
def _from_table() -> None:
    """Copy names and data tables out of the one table (again when a code is registered)."""
    FUNCTION_NAMES.clear()
    _TABLES.clear()
    for code, f in FUNCTIONS.items():
        FUNCTION_NAMES[code] = f.name
        if f.table is not None:
            _TABLES[code] = f.table
