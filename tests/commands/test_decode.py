"""`mbmon decode`: bare PDUs in JSON, values as numbers, the CRC a
frame should have had, odd hex digits, and the help's HRSS example."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

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


def test_bytes_with_a_bad_crc_that_frame_as_rtu_are_said_to_be_an_rtu_frame() -> None:
    out = decode("01 03 00 00 00 0A C5 CE").stdout
    assert "framing: RTU ADU with a bad CRC" in out
    assert "CRC: BAD (the frame has C5 CE, expected C5 CD)" in out
    assert "meaning: Read Holding Registers 0..9" in out
    assert "Read Coils" not in out and "malformed" not in out
    obj = json.loads(decode("--json", "01 03 00 00 00 0A C5 CE").stdout)
    assert (obj["framing"], obj["crc_ok"], obj["unit"], obj["fc"]) == ("rtu", False, 1, 3)
    assert "bad CRC" in obj["framing_note"]
    # what is a well-formed PDU stays a PDU; --pdu still reads the bytes as one
    assert "framing: PDU" in decode("02 01 2C 00 05").stdout
    assert "framing: PDU" in decode("--pdu", "01 03 00 00 00 0A C5 CE").stdout
    # an exception answer with a bad CRC too
    assert "framing: RTU ADU with a bad CRC" in decode("11 83 02 00 00").stdout


def _frames_of(adu: bytes, transport: str) -> list[object]:
    """The frames the pipeline's own stream decoder makes of ``adu`` (a request)."""
    from mbmon.model import Direction, Frame, Stream, Transport
    from mbmon.protocol.mbap import MbapDecoder
    from mbmon.protocol.rtu import RtuDecoder

    if transport == "rtu":
        stream = Stream(0, Transport.RTU, "client", "server")
        decoder: object = RtuDecoder(stream, Direction.C2S)
    else:
        stream = Stream(0, Transport.TCP, "client", "server")
        decoder = MbapDecoder(stream, Direction.C2S)
    out = [*decoder.feed(adu, 0.0), *decoder.flush(0.0)]  # type: ignore[attr-defined]
    return [x for x in out if isinstance(x, Frame)]


def test_decode_prints_format_py_lines_of_the_frame_the_pipeline_makes() -> None:
    """decode's text is :func:`mbmon.details.frame_text` of the frame the stream decoders
    make from the same bytes: one text for a frame, typed or captured."""
    from mbmon.details import frame_text

    for adu, transport in (
        ("01 03 00 00 00 0A C5 CD", "rtu"),
        ("00 01 00 00 00 06 01 03 00 00 00 01", "tcp"),
        ("11 10 00 C9 00 03 06 00 03 00 00 00 01 4F 46", "rtu"),
    ):
        raw = bytes.fromhex(adu)
        if transport == "rtu":
            from mbmon.protocol.crc import add_crc

            raw = add_crc(raw[:-2])
        (frame,) = _frames_of(raw, transport)
        out = decode(raw.hex(" ")).stdout
        assert out.splitlines() == frame_text(frame), (adu, out)  # type: ignore[arg-type]


def test_the_details_of_a_bad_crc_name_the_expected_crc() -> None:
    """format.py's CRC line (decode's and the monitor's details pane): a bad CRC says
    which CRC the frame has and which it should have."""
    from dataclasses import replace

    from mbmon.details import frame_details
    from mbmon.protocol.crc import add_crc

    (good,) = _frames_of(add_crc(bytes.fromhex("0103000A0001")), "rtu")
    bad = replace(good, raw=good.raw[:-2] + b"\xab\xcd", crc_ok=False)  # type: ignore[type-var]
    texts = [text for text, _span in frame_details(bad)]
    expected = add_crc(bytes.fromhex("0103000A0001"))[-2:].hex(" ").upper()
    assert f"CRC: BAD (the frame has AB CD, expected {expected})" in texts
    assert "CRC: ok" in [text for text, _span in frame_details(good)]  # type: ignore[arg-type]


def _typed_records(data: bytes, framing: str, response: bool = False) -> list[object]:
    """Every record the one flow makes of typed bytes: TypedFrameSource → hub → pipeline."""
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline
    from mbmon.sources.base import run_sources
    from mbmon.sources.typed import TypedFrameSource

    records: list[object] = []

    class Keep:
        def on_record(self, record: object) -> None:
            records.append(record)

    hub = Hub(Pipeline(), [Keep()])
    source = TypedFrameSource(data, framing, response=response)  # type: ignore[arg-type]
    source.open(hub)
    run_sources(hub, [source])
    hub.close()
    return records


# (typed hex, framing, the monitor line, the CRC line): requests typed alone, RTU frames
# whose CRC fails, an exception answer with a bad CRC
ONE_PATH = [
    ("01 03 00 00 00 0A C5 CD", "rtu", "03 00 00 00 0A", "CRC: ok"),
    ("00 01 00 00 00 06 01 03 00 00 00 01", "tcp", "03 00 00 00 01", None),
    ("02 01 2C 00 05", "pdu", "02 01 2C 00 05", None),
    (
        "01 03 00 00 00 0A C5 CE",
        "rtu",
        "03 00 00 00 0A",
        "CRC: BAD (the frame has C5 CE, expected C5 CD)",
    ),
    (
        "01 03 00 00 00 0A C5 CC",
        "rtu",
        "03 00 00 00 0A",
        "CRC: BAD (the frame has C5 CC, expected C5 CD)",
    ),
    ("11 83 02 00 00", "rtu", "83 02", "CRC: BAD (the frame has 00 00, expected C1 34)"),
]


@pytest.mark.parametrize(("typed", "framing", "line", "crc"), ONE_PATH)
def test_decode_prints_exactly_the_records_of_the_typed_source(
    typed: str, framing: str, line: str, crc: str | None
) -> None:
    """One path: a request typed alone is one record (never "no response": nothing after
    it was observed), and an RTU frame whose CRC fails is that frame with its CRC
    verdict (not noise, as on a bus); decode prints frame_text of those records."""
    from mbmon.details import frame_text

    data = bytes.fromhex(typed)
    records = _typed_records(data, framing)
    assert [r.frame.raw for r in records] == [data]  # type: ignore[attr-defined]
    (record,) = records
    out = decode(f"--{framing}", typed).stdout.splitlines()
    assert out[0] == line
    framing_text = out[1].split(": ", 1)[1]
    assert out == frame_text(record.frame, record.notes, framing=framing_text)  # type: ignore[attr-defined]
    assert ("  " + crc in out[2:]) if crc else not any("CRC" in x for x in out)
