"""CRC16/Modbus against spec vectors, a real RTU log and pymodbus as an oracle."""

from __future__ import annotations

import importlib
import re
import threading
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.protocol.crc import CRC_TABLE, add_crc, check_crc, crc16, crc_bytes

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "captures" / "real"
SOLIS = REAL / "rtu_log__candlerb__solis_packet_log.md"

# (address + PDU, CRC bytes as on the wire)
VECTORS = [
    ("01 03 00 00 00 0A", "C5 CD"),
    ("11 03 00 6B 00 03", "76 87"),  # spec read holding registers example, unit 17
    ("01 04 0B B7 00 01", "83 C8"),  # Solis log: read input register 2999
    ("01 84 02", "C2 C1"),  # Solis log: exception 02
    ("01 04 80 E8 00 01", "98 3E"),  # Solis log: read input register 33000
    ("01 04 02 31 05", "6C A3"),  # Solis log: its response
    ("01 10 A7 F8 00 06", "E2 8E"),  # Solis log: write multiple response
    ("", "FF FF"),  # nothing processed: the initial value
]


@pytest.mark.parametrize(("body", "crc"), VECTORS)
def test_vectors(body: str, crc: str) -> None:
    data = bytes.fromhex(body)
    wire = bytes.fromhex(crc)
    assert crc_bytes(data) == wire
    assert crc16(data) == wire[0] | (wire[1] << 8)
    assert add_crc(data) == data + wire
    if data:
        assert check_crc(data + wire)


def test_check_value() -> None:
    # The CRC-16/MODBUS catalogue check value for "123456789".
    assert crc16(b"123456789") == 0x4B37


def test_buffer_types() -> None:
    data = bytes.fromhex("0103000000 0A")
    assert crc16(bytearray(data)) == crc16(memoryview(data)) == crc16(data) == 0xCDC5
    assert check_crc(memoryview(bytes.fromhex("01030000000AC5CD")))
    assert check_crc(bytearray(bytes.fromhex("01030000000AC5CD")))


def test_table() -> None:
    assert len(CRC_TABLE) == 256
    assert CRC_TABLE[0] == 0 and CRC_TABLE[1] == 0xC0C1 and CRC_TABLE[255] == 0x4040


def test_check_crc_rejects() -> None:
    good = bytes.fromhex("01030000000AC5CD")
    assert not check_crc(good[:-1] + b"\xce")  # last byte wrong
    assert not check_crc(bytes.fromhex("01030000000ACDC5"))  # bytes swapped
    assert not check_crc(b"\x01\x03\x00\x00\x00\x0b\xc5\xcd")  # body changed
    assert not check_crc(b"")
    assert not check_crc(b"\xff\xff")  # 2 bytes: CRC of nothing, but too short
    assert not check_crc(b"\x00")


def _solis_frames() -> list[tuple[str, bytes]]:
    if not SOLIS.is_file():
        pytest.skip(f"{SOLIS.name} absent: ../shared/captures/real absent")
    frames = []
    for line in SOLIS.read_text().splitlines():
        m = re.fullmatch(r"-([<>])([0-9A-Fa-f]+)\s*", line)
        if m:
            frames.append((m.group(1), bytes.fromhex(m.group(2))))
    return frames


def test_solis_log_frames() -> None:
    frames = _solis_frames()
    assert len(frames) >= 20
    for _, frame in frames:
        assert check_crc(frame), frame.hex()
        corrupted = bytes([frame[0] ^ 0x01]) + frame[1:]
        assert not check_crc(corrupted)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_against_pymodbus(data: bytes) -> None:
    from pymodbus.framer.rtu import FramerRTU

    assert crc_bytes(data) == FramerRTU.compute_CRC(data).to_bytes(2, "big")
    assert check_crc(add_crc(data)) == (len(data) >= 1)


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=1, max_size=64), st.integers(0, 7), st.data())
def test_single_bit_error_detected(data: bytes, bit: int, pick: st.DataObject) -> None:
    adu = bytearray(add_crc(data))
    i = pick.draw(st.integers(0, len(adu) - 1))
    adu[i] ^= 1 << bit
    assert not check_crc(adu)


def _first_uses_at_once(module: Any, frame: bytes, threads: int) -> list[object]:
    """``crc_ok_at(frame)`` from ``threads`` threads released together: each answer,
    or the exception a thread got instead."""
    start = threading.Barrier(threads)
    results: list[object] = []

    def check() -> None:
        start.wait()
        try:
            results.append(module.crc_ok_at(frame, 0, len(frame)))
        except Exception as exc:  # the test reports it
            results.append(exc)

    workers = [threading.Thread(target=check) for _ in range(threads)]
    for t in workers:
        t.start()
    for t in workers:
        t.join()
    return results


def test_crc_ok_at_first_use_from_many_threads_at_once() -> None:
    """The two-bytes-per-step tables are built on first use. The proxy decodes
    on more than one thread (the RTU link and the hub), so a first use racing
    another first use must see whole tables, never half-built ones (CI saw
    ``IndexError`` in ``crc_ok_at`` from exactly that)."""
    import mbmon.protocol.crc as crc_module

    frame = bytes.fromhex("01030000000AC5CD")
    try:
        for _round in range(5):
            fresh = importlib.reload(crc_module)  # tables empty again
            assert _first_uses_at_once(fresh, frame, 8) == [True] * 8
    finally:
        importlib.reload(crc_module)
