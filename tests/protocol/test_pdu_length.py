"""pdu_length: RTU length prediction for every function code."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from mbmon.protocol.pdu import NEED_MORE, decode_pdu, pdu_length

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "captures" / "real"
SOLIS = REAL / "rtu_log__candlerb__solis_packet_log.md"

# Complete PDUs (spec examples): pdu_length of the whole PDU is its length, and
# every shorter prefix is NEED_MORE or already that length.
COMPLETE = [
    ("01 00 13 00 13", False),
    ("01 03 CD 6B 05", True),
    ("02 00 C4 00 16", False),
    ("02 03 AC DB 35", True),
    ("03 00 6B 00 03", False),
    ("03 06 02 2B 00 00 00 64", True),
    ("04 00 08 00 01", False),
    ("04 02 00 0A", True),
    ("05 00 AC FF 00", False),
    ("05 00 AC FF 00", True),
    ("06 00 01 00 03", False),
    ("06 00 01 00 03", True),
    ("07", False),
    ("07 6D", True),
    ("08 00 0A 00 00", False),
    ("08 00 0A 00 00", True),
    ("08 00 15 00 03", False),
    ("0B", False),
    ("0B FF FF 01 08", True),
    ("0C", False),
    ("0C 08 00 00 01 08 01 21 20 00", True),
    ("0F 00 13 00 0A 02 CD 01", False),
    ("0F 00 13 00 0A", True),
    ("10 00 01 00 02 04 00 0A 01 02", False),
    ("10 00 01 00 02", True),
    ("11", False),
    ("11 04 48 52 53 FF", True),
    ("14 0E 06 00 04 00 01 00 02 06 00 03 00 09 00 02", False),
    ("14 0C 05 06 0D FE 00 20 05 06 33 CD 00 40", True),
    ("15 0D 06 00 04 00 07 00 03 06 AF 04 BE 10 0D", False),
    ("15 0D 06 00 04 00 07 00 03 06 AF 04 BE 10 0D", True),
    ("16 00 04 00 F2 00 25", False),
    ("16 00 04 00 F2 00 25", True),
    ("17 00 03 00 06 00 0E 00 03 06 00 FF 00 FF 00 FF", False),
    ("17 0C 00 FE 0A CD 00 01 00 03 00 0D 00 FF", True),
    ("18 04 DE", False),
    ("18 00 06 00 02 01 B8 12 84", True),
    ("2B 0E 01 00", False),
    ("81 02", True),
    ("90 04", True),
    ("AB 01", True),
    ("C1 01", True),
]


@pytest.mark.parametrize(("text", "response"), COMPLETE)
def test_complete(text: str, response: bool) -> None:
    pdu = bytes.fromhex(text)
    assert pdu_length(pdu, response) == len(pdu)
    assert pdu_length(memoryview(pdu), response) == len(pdu)
    assert pdu_length(bytearray(pdu) + b"\x00\x00\xaa", response) == len(pdu)  # + CRC etc.
    for cut in range(len(pdu)):
        assert pdu_length(pdu[:cut], response) in (NEED_MORE, len(pdu)), cut


@pytest.mark.parametrize(
    ("text", "response", "expected"),
    [
        ("", False, NEED_MORE),
        ("", True, NEED_MORE),
        ("03", False, 5),
        ("03", True, NEED_MORE),
        ("03 FA", True, 252),
        ("01 00", True, 2),
        ("10 00 01 00", False, NEED_MORE),
        ("10 00 01 00 02", False, NEED_MORE),
        ("10 00 01 00 02 F6", False, 252),
        ("0F 00 01 00 02 01", False, 7),
        ("10", True, 5),
        ("0F", True, 5),
        ("08", False, NEED_MORE),
        ("08 00", True, NEED_MORE),
        ("08 00 01", True, 5),
        ("08 00 00", False, None),  # Return Query Data echoes any length
        ("08 00 00", True, None),
        ("08 00 15", True, None),  # Modbus Plus statistics
        ("08 00 15", False, 5),
        ("07", True, 2),
        ("0B", True, 5),
        ("0C 0A", True, 12),
        ("11 05", True, 7),
        ("14 07", False, 9),
        ("14 04", True, 6),
        ("15 0D", True, 15),
        ("16", False, 7),
        ("17 00 03 00 06 00 0E 00 03", False, NEED_MORE),
        ("17 00 03 00 06 00 0E 00 03 02", False, 12),
        ("17 02", True, 4),
        ("18", False, 3),
        ("18 00", True, NEED_MORE),
        ("18 00 06", True, 9),
        ("18 01 00", True, 259),
        ("2B", False, NEED_MORE),
        ("2B 0E", False, 4),
        ("2B 0D 00", False, None),
        ("2B", True, None),
        ("2B 0E 01 01 00 00 00", True, None),
        ("81", True, 2),
        ("83", False, None),  # exception bit in a request: not a request
        ("41 00 00", False, None),
        ("41", True, None),
        ("64", True, None),
        ("00", False, None),
        ("09", False, None),
    ],
)
def test_prefixes(text: str, response: bool, expected: int | None) -> None:
    assert pdu_length(bytes.fromhex(text), response) == expected


def test_solis_frames() -> None:
    if not SOLIS.is_file():
        pytest.skip(f"{SOLIS.name} absent: ../shared/captures/real absent")
    n = 0
    for line in SOLIS.read_text().splitlines():
        m = re.fullmatch(r"-([<>])([0-9A-Fa-f]+)\s*", line)
        if not m:
            continue
        response = m.group(1) == "<"
        adu = bytes.fromhex(m.group(2))
        pdu = adu[1:-2]
        assert pdu_length(adu[1:], response) == len(pdu), adu.hex()
        decoded = decode_pdu(pdu, response)
        assert decoded.malformed is None, (adu.hex(), decoded.malformed)
        n += 1
    assert n >= 20
