"""PDU decoding against the Modbus Application Protocol v1.1b3 examples and the HIWIN manual."""

from __future__ import annotations

from typing import Any

import pytest

from mbmon.model import Kind, Pdu
from mbmon.protocol.pdu import (
    DIAGNOSTIC_NAMES,
    EXCEPTION_NAMES,
    FUNCTION_NAMES,
    MEI_OBJECT_NAMES,
    decode_pdu,
    table_of,
)


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def req(text: str) -> Pdu:
    return decode_pdu(h(text), response=False)


def resp(text: str, request: str | None = None) -> Pdu:
    return decode_pdu(h(text), response=True, request=req(request) if request else None)


def check(pdu: Pdu, kind: Kind, fc: int, **expect: Any) -> None:
    """Every common field named in ``expect`` must match; the rest must be None."""
    assert pdu.kind is kind
    assert pdu.fc == fc
    assert pdu.malformed is None, pdu.malformed
    fields = expect.pop("fields", {})
    for name in ("exception_code", "address", "count", "byte_count", "values"):
        assert getattr(pdu, name) == expect.pop(name, None), name
    assert not expect
    assert dict(pdu.fields) == fields


# ------------------------------------------------------------------ spec examples


def test_read_coils() -> None:
    q = req("01 00 13 00 13")
    check(q, Kind.REQUEST, 0x01, address=19, count=19)
    bits = (*(1, 0, 1, 1, 0, 0, 1, 1), *(1, 1, 0, 1, 0, 1, 1, 0), *(1, 0, 1))  # CD 6B 05
    check(resp("01 03 CD 6B 05", "01 00 13 00 13"), Kind.RESPONSE, 0x01, byte_count=3, values=bits)
    # Without the request every bit of the bytes is kept.
    check(resp("01 03 CD 6B 05"), Kind.RESPONSE, 0x01, byte_count=3, values=(*bits, 0, 0, 0, 0, 0))


def test_read_discrete_inputs() -> None:
    check(req("02 00 C4 00 16"), Kind.REQUEST, 0x02, address=196, count=22)
    bits = (*(0, 0, 1, 1, 0, 1, 0, 1), *(1, 1, 0, 1, 1, 0, 1, 1), *(1, 0, 1, 0, 1, 1))  # AC DB 35
    check(resp("02 03 AC DB 35", "02 00 C4 00 16"), Kind.RESPONSE, 0x02, byte_count=3, values=bits)


def test_read_holding_registers() -> None:
    check(req("03 00 6B 00 03"), Kind.REQUEST, 0x03, address=107, count=3)
    check(
        resp("03 06 02 2B 00 00 00 64", "03 00 6B 00 03"),
        Kind.RESPONSE,
        0x03,
        byte_count=6,
        values=(555, 0, 100),
    )


def test_read_input_registers() -> None:
    check(req("04 00 08 00 01"), Kind.REQUEST, 0x04, address=8, count=1)
    check(resp("04 02 00 0A"), Kind.RESPONSE, 0x04, byte_count=2, values=(10,))


def test_write_single_coil() -> None:
    check(req("05 00 AC FF 00"), Kind.REQUEST, 0x05, address=172, count=1, values=(1,))
    check(resp("05 00 AC FF 00"), Kind.RESPONSE, 0x05, address=172, count=1, values=(1,))
    check(req("05 00 AC 00 00"), Kind.REQUEST, 0x05, address=172, count=1, values=(0,))


def test_write_single_register() -> None:
    check(req("06 00 01 00 03"), Kind.REQUEST, 0x06, address=1, count=1, values=(3,))
    check(resp("06 00 01 00 03"), Kind.RESPONSE, 0x06, address=1, count=1, values=(3,))


def test_read_exception_status() -> None:
    check(req("07"), Kind.REQUEST, 0x07)
    check(resp("07 6D"), Kind.RESPONSE, 0x07, fields={"status": 0x6D})


def test_diagnostics() -> None:
    fields = {"sub_function": 0, "data": h("A5 37")}
    check(req("08 00 00 A5 37"), Kind.REQUEST, 0x08, values=(0xA537,), fields=fields)
    check(
        resp("08 00 00 A5 37", "08 00 00 A5 37"),
        Kind.RESPONSE,
        0x08,
        values=(0xA537,),
        fields=fields,
    )
    # Return Bus Message Count (0x0B): request data 0000, reply the counter.
    check(
        resp("08 00 0B 01 2C"),
        Kind.RESPONSE,
        0x08,
        values=(300,),
        fields={"sub_function": 0x0B, "data": h("01 2C")},
    )
    # Return Query Data echoes any length; odd lengths give no words.
    check(
        req("08 00 00 01 02 03"),
        Kind.REQUEST,
        0x08,
        fields={"sub_function": 0, "data": h("01 02 03")},
    )


def test_get_comm_event_counter() -> None:
    check(req("0B"), Kind.REQUEST, 0x0B)
    check(
        resp("0B FF FF 01 08"),
        Kind.RESPONSE,
        0x0B,
        fields={"status": 0xFFFF, "event_count": 0x108},
    )


def test_get_comm_event_log() -> None:
    check(req("0C"), Kind.REQUEST, 0x0C)
    check(
        resp("0C 08 00 00 01 08 01 21 20 00"),
        Kind.RESPONSE,
        0x0C,
        byte_count=8,
        fields={"status": 0, "event_count": 0x108, "message_count": 0x121, "events": h("20 00")},
    )


def test_write_multiple_coils() -> None:
    check(
        req("0F 00 13 00 0A 02 CD 01"),
        Kind.REQUEST,
        0x0F,
        address=19,
        count=10,
        byte_count=2,
        values=(1, 0, 1, 1, 0, 0, 1, 1, 1, 0),
    )
    check(resp("0F 00 13 00 0A"), Kind.RESPONSE, 0x0F, address=19, count=10)


def test_write_multiple_registers() -> None:
    check(
        req("10 00 01 00 02 04 00 0A 01 02"),
        Kind.REQUEST,
        0x10,
        address=1,
        count=2,
        byte_count=4,
        values=(10, 258),
    )
    check(resp("10 00 01 00 02"), Kind.RESPONSE, 0x10, address=1, count=2)


def test_report_server_id() -> None:
    check(req("11"), Kind.REQUEST, 0x11)
    check(
        resp("11 04 48 52 53 FF"),
        Kind.RESPONSE,
        0x11,
        byte_count=4,
        fields={"server_id": b"HRS", "run_indicator": 0xFF},
    )
    check(
        resp("11 02 01 00"),
        Kind.RESPONSE,
        0x11,
        byte_count=2,
        fields={"server_id": b"\x01", "run_indicator": 0x00},
    )


READ_FILE_REQ = "14 0E 06 00 04 00 01 00 02 06 00 03 00 09 00 02"


def test_read_file_record() -> None:
    asked = (
        {"reference_type": 6, "file_number": 4, "record_number": 1, "record_length": 2},
        {"reference_type": 6, "file_number": 3, "record_number": 9, "record_length": 2},
    )
    check(req(READ_FILE_REQ), Kind.REQUEST, 0x14, byte_count=14, fields={"records": asked})
    got = (
        {"reference_type": 6, "record_length": 2, "data": (0x0DFE, 0x0020)},
        {"reference_type": 6, "record_length": 2, "data": (0x33CD, 0x0040)},
    )
    response = "14 0C 05 06 0D FE 00 20 05 06 33 CD 00 40"
    check(resp(response), Kind.RESPONSE, 0x14, byte_count=12, fields={"records": got})
    # With the request, each sub-response learns its file and record number.
    paired = tuple(
        {**g, "file_number": a["file_number"], "record_number": a["record_number"]}
        for g, a in zip(got, asked, strict=True)
    )
    check(
        resp(response, READ_FILE_REQ),
        Kind.RESPONSE,
        0x14,
        byte_count=12,
        fields={"records": paired},
    )


def test_write_file_record() -> None:
    text = "15 0D 06 00 04 00 07 00 03 06 AF 04 BE 10 0D"
    records = (
        {
            "reference_type": 6,
            "file_number": 4,
            "record_number": 7,
            "record_length": 3,
            "data": (0x06AF, 0x04BE, 0x100D),
        },
    )
    check(req(text), Kind.REQUEST, 0x15, byte_count=13, fields={"records": records})
    check(resp(text, text), Kind.RESPONSE, 0x15, byte_count=13, fields={"records": records})


def test_mask_write_register() -> None:
    fields = {"and_mask": 0x00F2, "or_mask": 0x0025}
    check(req("16 00 04 00 F2 00 25"), Kind.REQUEST, 0x16, address=4, fields=fields)
    check(resp("16 00 04 00 F2 00 25"), Kind.RESPONSE, 0x16, address=4, fields=fields)


RW_REQ = "17 00 03 00 06 00 0E 00 03 06 00 FF 00 FF 00 FF"


def test_read_write_multiple_registers() -> None:
    check(
        req(RW_REQ),
        Kind.REQUEST,
        0x17,
        address=3,
        count=6,
        fields={
            "write_address": 14,
            "write_count": 3,
            "write_byte_count": 6,
            "write_values": (255, 255, 255),
        },
    )
    check(
        resp("17 0C 00 FE 0A CD 00 01 00 03 00 0D 00 FF", RW_REQ),
        Kind.RESPONSE,
        0x17,
        byte_count=12,
        values=(0xFE, 0x0ACD, 1, 3, 0x0D, 0xFF),
    )


def test_read_fifo_queue() -> None:
    check(req("18 04 DE"), Kind.REQUEST, 0x18, address=1246)
    check(
        resp("18 00 06 00 02 01 B8 12 84", "18 04 DE"),
        Kind.RESPONSE,
        0x18,
        byte_count=6,
        values=(440, 4740),
        fields={"fifo_count": 2},
    )


def _object(object_id: int, text: str) -> str:
    data = text.encode()
    return f"{object_id:02X} {len(data):02X} {data.hex()}"


def test_read_device_identification() -> None:
    check(
        req("2B 0E 01 00"),
        Kind.REQUEST,
        0x2B,
        fields={"mei_type": 0x0E, "read_device_id_code": 1, "object_id": 0},
    )
    objects = ((0, "Company identification"), (1, "Product code XX"), (2, "V2.11"))
    body = " ".join(_object(i, t) for i, t in objects)
    check(
        resp("2B 0E 01 01 00 00 03 " + body, "2B 0E 01 00"),
        Kind.RESPONSE,
        0x2B,
        fields={
            "mei_type": 0x0E,
            "read_device_id_code": 1,
            "conformity_level": 1,
            "more_follows": 0,
            "next_object_id": 0,
            "number_of_objects": 3,
            "objects": objects,
        },
    )
    # The spec's second example: more follows, next object 2; Latin-1 fallback.
    check(
        resp("2B 0E 01 82 FF 02 01 00 03 48 49 57"),
        Kind.RESPONSE,
        0x2B,
        fields={
            "mei_type": 0x0E,
            "read_device_id_code": 1,
            "conformity_level": 0x82,
            "more_follows": 0xFF,
            "next_object_id": 2,
            "number_of_objects": 1,
            "objects": ((0, "HIW"),),
        },
    )
    latin = resp("2B 0E 01 01 00 00 01 00 02 C4 FF").fields["objects"]
    assert latin == ((0, "\u00c4\u00ff"),)
    utf8 = resp("2B 0E 01 01 00 00 01 00 02 C3 84").fields["objects"]
    assert utf8 == ((0, "\u00c4"),)


def test_canopen_mei_kept_raw() -> None:
    check(req("2B 0D 01 02 03"), Kind.REQUEST, 0x2B, fields={"mei_type": 0x0D, "data": h("010203")})
    check(resp("2B 0D"), Kind.RESPONSE, 0x2B, fields={"mei_type": 0x0D, "data": b""})


@pytest.mark.parametrize("code", [1, 2, 3, 4, 5, 6, 8, 0x0A, 0x0B, 0x42])
@pytest.mark.parametrize("fc", [0x01, 0x03, 0x10, 0x17, 0x2B, 0x41])
def test_exceptions(fc: int, code: int) -> None:
    pdu = decode_pdu(bytes((fc | 0x80, code)), response=True)
    check(pdu, Kind.EXCEPTION, fc, exception_code=code)
    assert pdu.raw == bytes((fc | 0x80, code))


def test_spec_exception_example() -> None:
    # Spec figure: read input registers 01 04 A1 00 01 answered with 84 02 -> illegal address.
    pdu = resp("84 02", "04 A1 00 00 01")
    check(pdu, Kind.EXCEPTION, 0x04, exception_code=2)
    assert EXCEPTION_NAMES[pdu.exception_code or 0] == "Illegal Data Address"


@pytest.mark.parametrize("fc", [0x41, 0x48, 0x64, 0x6E, 0x09, 0x0D, 0x12, 0x7F])
def test_user_defined_codes_kept_raw(fc: int) -> None:
    for response in (False, True):
        pdu = decode_pdu(bytes((fc, 1, 2, 3)), response)
        kind = Kind.RESPONSE if response else Kind.REQUEST
        check(pdu, kind, fc, fields={"data": h("01 02 03")})
    check(decode_pdu(bytes((fc,)), True), Kind.RESPONSE, fc, fields={"data": b""})


def test_raw_is_input() -> None:
    data = h("03 06 02 2B 00 00 00 64")
    assert decode_pdu(data, True).raw == data
    assert decode_pdu(bytearray(data), True).raw == data
    assert decode_pdu(memoryview(data), True).raw == data
    assert type(decode_pdu(memoryview(data), True).raw) is bytes


# ------------------------------------------------------------------ HIWIN manual §5.5.2


def test_hiwin_read_discrete_inputs() -> None:
    q = req("02 01 2C 00 05")
    check(q, Kind.REQUEST, 0x02, address=300, count=5)
    check(
        decode_pdu(h("02 01 13"), True, q),
        Kind.RESPONSE,
        0x02,
        byte_count=1,
        values=(1, 1, 0, 0, 1),
    )


def test_hiwin_read_coils() -> None:
    check(req("01 01 2C 00 05"), Kind.REQUEST, 0x01, address=300, count=5)
    check(
        resp("01 01 13", "01 01 2C 00 05"),
        Kind.RESPONSE,
        0x01,
        byte_count=1,
        values=(1, 1, 0, 0, 1),
    )


def test_hiwin_write_coils() -> None:
    check(
        req("0F 01 2C 00 05 01 13"),
        Kind.REQUEST,
        0x0F,
        address=300,
        count=5,
        byte_count=1,
        values=(1, 1, 0, 0, 1),
    )
    check(resp("0F 01 2C 00 05"), Kind.RESPONSE, 0x0F, address=300, count=5)


def test_hiwin_read_input_registers() -> None:
    check(req("04 00 64 00 02"), Kind.REQUEST, 0x04, address=100, count=2)
    check(
        resp("04 04 00 5A 00 00", "04 00 64 00 02"),
        Kind.RESPONSE,
        0x04,
        byte_count=4,
        values=(90, 0),
    )


def test_hiwin_read_holding_registers() -> None:
    check(req("03 01 90 00 02"), Kind.REQUEST, 0x03, address=400, count=2)
    check(
        resp("03 04 01 90 00 00", "03 01 90 00 02"),
        Kind.RESPONSE,
        0x03,
        byte_count=4,
        values=(400, 0),
    )


def test_hiwin_write_holding_registers() -> None:
    check(
        req("10 00 C9 00 03 06 00 6F 00 DE 01 4D"),
        Kind.REQUEST,
        0x10,
        address=201,
        count=3,
        byte_count=6,
        values=(111, 222, 333),
    )
    check(resp("10 00 C9 00 03"), Kind.RESPONSE, 0x10, address=201, count=3)


# ------------------------------------------------------------------ tables


def test_name_tables() -> None:
    assert FUNCTION_NAMES[0x03] == "Read Holding Registers"
    assert FUNCTION_NAMES[0x17] == "Read/Write Multiple Registers"
    assert set(FUNCTION_NAMES) == {
        0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x08, 0x0B, 0x0C,
        0x0F, 0x10, 0x11, 0x14, 0x15, 0x16, 0x17, 0x18, 0x2B,
    }  # fmt: skip
    assert set(EXCEPTION_NAMES) == {1, 2, 3, 4, 5, 6, 8, 0x0A, 0x0B}
    assert EXCEPTION_NAMES[0x0B] == "Gateway Target Device Failed To Respond"
    assert DIAGNOSTIC_NAMES[0x00] == "Return Query Data"
    assert DIAGNOSTIC_NAMES[0x14] == "Clear Overrun Counter and Flag"
    assert {0x00, 0x01, 0x02, 0x03, 0x04, 0x0A, 0x12, 0x14} <= set(DIAGNOSTIC_NAMES)
    assert [MEI_OBJECT_NAMES[i] for i in range(7)] == [
        "VendorName",
        "ProductCode",
        "MajorMinorRevision",
        "VendorUrl",
        "ProductName",
        "ModelName",
        "UserApplicationName",
    ]


@pytest.mark.parametrize(
    ("fc", "table"),
    [
        (0x01, "coil"),
        (0x05, "coil"),
        (0x0F, "coil"),
        (0x02, "discrete_input"),
        (0x03, "holding_register"),
        (0x06, "holding_register"),
        (0x10, "holding_register"),
        (0x16, "holding_register"),
        (0x17, "holding_register"),
        (0x04, "input_register"),
        (0x83, "holding_register"),
        (0x07, None),
        (0x08, None),
        (0x14, None),
        (0x2B, None),
        (0x41, None),
    ],
)
def test_table_of(fc: int, table: str | None) -> None:
    assert table_of(fc) == table
