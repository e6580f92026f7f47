"""`mbmon decode` (issue 8 item 20): bare PDUs in JSON, values as numbers, the CRC a
frame should have had, odd hex digits, and the help's HRSS example."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def decode(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mbmon", "decode", *args],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )


def test_a_bare_pdu_has_transport_pdu_and_no_unit() -> None:
    obj = json.loads(decode("--json", "03", "00", "00", "00", "0A").stdout)
    assert obj["transport"] == "pdu" and obj["unit"] is None and obj["framing"] == "pdu"
    rtu = json.loads(decode("--json", "01 03 00 00 00 0A C5 CD").stdout)
    assert rtu["transport"] == "rtu" and rtu["unit"] == 1


def test_values_print_as_numbers_never_tuples() -> None:
    out = decode("17 00 01 00 02 00 03 00 02 04 00 0A 00 0B").stdout
    assert "write values: 10, 11" in out
    assert "(" not in out.split("meaning:")[1].split("\n", 1)[1]


def test_a_bad_crc_says_which_crc_was_expected() -> None:
    out = decode("--rtu", "01 03 00 00 00 0A C5 CC").stdout
    assert "CRC: BAD (the frame has C5 CC, expected C5 CD)" in out
    assert "CRC: ok" in decode("01 03 00 00 00 0A C5 CD").stdout


def test_odd_hex_digits_say_so() -> None:
    for typed in (["ABC"], ["0001", "03A"], ["0x123"]):
        res = decode(*typed)
        assert res.returncode == 2
        assert "odd number of hex digits" in res.stderr and "usage: mbmon decode" in res.stderr
    assert decode("1 3 0 0 0 1").returncode == 0  # lone digits are bytes


def test_the_helps_hrss_example_is_a_real_command() -> None:
    help_text = decode("--help").stdout
    example = next(line for line in help_text.splitlines() if "--profile hrss" in line)
    hex_bytes = example.split("--profile hrss", 1)[1].split()
    out = decode("--profile", "hrss", *hex_bytes).stdout
    assert "note: R201 = JOG (3)" in out and "note: written: JOG A1 +" in out
