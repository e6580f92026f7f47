"""Monitor lines exactly as the robot's Modbus Monitor shows them (manual §5.5.2, Table 57)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.format import (
    View,
    format_time,
    generic_note,
    json_line,
    monitor_hex,
    record_line,
    record_to_json,
)
from mbmon.jsoncache import SEEN_ONCE_SIZE
from mbmon.jsonfmt import record_json_bytes
from mbmon.model import Direction, Event, EventKind, Frame, Record, RecordKind, Stream, Transport
from mbmon.protocol.pdu import decode_pdu

REPO = Path(__file__).resolve().parents[1]
REAL = REPO / ".." / "shared" / "captures" / "real"

TCP = Stream(3, Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")
BUS = Stream(0, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0")

# (query as the manual prints it, response as the manual prints it) — §5.5.2.2 .. §5.5.2.7
MANUAL = [
    ("02 01 2C 00 05", "02 01 13"),
    ("01 01 2C 00 05", "01 01 13"),
    ("0F 01 2C 00 05 01 13", "0F 01 2C 00 05"),
    ("04 00 64 00 02", "04 04 00 5a 00 00"),
    ("03 01 90 00 02", "03 04 01 90 00 00"),
    ("10 00 c9 00 03 06 00 6f 00 de 01 4d", "10 00 c9 00 03"),
]


def _frame(hex_pdu: str, response: bool, stream: Stream = TCP, request: Frame | None = None):
    raw = bytes.fromhex(hex_pdu)
    pdu = decode_pdu(raw, response, request.pdu if request else None)
    direction = Direction.S2C if response else Direction.C2S
    return Frame(1.5, stream, direction, 1, 7 if stream is TCP else None, pdu, raw)


@pytest.mark.parametrize(("query", "response"), MANUAL)
def test_manual_examples_byte_for_byte(query: str, response: str) -> None:
    req = _frame(query, False)
    resp = _frame(response, True, request=req)
    assert monitor_hex(req.pdu.raw) == query.upper()
    assert monitor_hex(resp.pdu.raw) == response.upper()
    line = record_line(Record(0, 1.5, RecordKind.REQUEST, TCP, frame=req), View())
    assert f"  {query.upper()}  | " in line


def test_generic_notes_use_the_request_for_reads() -> None:
    req = _frame("03 01 90 00 02", False)
    resp = _frame("03 04 01 90 00 00", True, request=req)
    assert generic_note(req.pdu) == "Read Holding Registers 400..401"
    assert generic_note(resp.pdu, req.pdu) == "Read Holding Registers 400..401 = 400, 0"
    bits = _frame("02 01 13", True, request=_frame("02 01 2C 00 05", False))
    assert generic_note(bits.pdu, decode_pdu(bytes.fromhex("02012C0005"), False)).endswith(
        "300..304 = 11001"
    )
    exc = _frame("83 02", True)
    assert generic_note(exc.pdu) == "Exception 02 Illegal Data Address (Read Holding Registers)"
    coil = _frame("05 00 00 FF 00", False)
    assert generic_note(coil.pdu) == "Write Single Coil 0 = ON"


def test_robot_labels_server_and_client() -> None:
    req = _frame("02 01 2C 00 05", False)
    resp = _frame("02 01 13", True, request=req)
    rec_q = Record(0, 1.5, RecordKind.REQUEST, TCP, frame=req)
    rec_r = Record(1, 1.6, RecordKind.RESPONSE, TCP, frame=resp, request=req, request_index=0)
    as_server = View(robot="10.0.0.2")
    assert "Receive from client  [u1 t7]  02 01 2C 00 05" in record_line(rec_q, as_server)
    assert "Send to client  [u1 t7]  02 01 13" in record_line(rec_r, as_server)
    as_client = View(robot="10.0.0.1:50000")
    assert "Send to server" in record_line(rec_q, as_client)
    assert "Receive from server" in record_line(rec_r, as_client)
    neutral = record_line(rec_q, View())
    assert "10.0.0.1:50000 → 10.0.0.2:502" in neutral
    other_port = View(robot="10.0.0.2:1502")
    assert "10.0.0.1:50000 → 10.0.0.2:502" in record_line(rec_q, other_port)


def test_rtu_robot_labels() -> None:
    req = _frame("03 01 90 00 02", False, stream=BUS)
    rec = Record(0, 1.5, RecordKind.REQUEST, BUS, frame=req)
    assert "Receive from client" in record_line(rec, View(robot="/dev/ttyUSB0"))
    assert "Send to server" in record_line(rec, View(robot="/dev/ttyUSB0", robot_is_client=True))
    assert "master → slave  [u1]" in record_line(rec, View())


def test_connect_lines() -> None:
    ev = Record(0, 1.0, RecordKind.EVENT, TCP, event=Event(1.0, TCP, EventKind.CONNECT))
    assert record_line(ev, View(robot="10.0.0.2")).endswith("Client 10.0.0.1:50000 connected")
    assert record_line(ev, View(robot="10.0.0.1")).endswith("Connected to server 10.0.0.2:502")
    gone = Event(2.0, TCP, EventKind.DISCONNECT, {"how": "rst", "by": "server"})
    rec = Record(1, 2.0, RecordKind.EVENT, TCP, event=gone)
    assert "disconnected (RST by server)" in record_line(rec, View(robot="10.0.0.2"))


def test_json_keys_are_stable() -> None:
    req = _frame("03 01 90 00 02", False)
    resp = _frame("03 04 01 90 00 00", True, request=req)
    rec = Record(
        1, 1.6, RecordKind.RESPONSE, TCP, frame=resp, request=req, request_index=0, latency=0.0021
    )
    obj = record_to_json(rec, View())
    for key in (
        "time",
        "stream",
        "src",
        "dst",
        "transport",
        "tid",
        "unit",
        "fc",
        "kind",
        "exception_code",
        "address",
        "count",
        "values",
        "pdu",
        "line",
        "notes",
        "crc_ok",
        "latency_ms",
        "malformed",
        "request_index",
    ):
        assert key in obj
    assert obj["src"] == "10.0.0.2:502" and obj["dst"] == "10.0.0.1:50000"
    assert obj["address"] == 400 and obj["count"] == 2 and obj["values"] == [400, 0]
    assert obj["pdu"] == "03 04 01 90 00 00" and obj["latency_ms"] == 2.1
    assert obj["kind"] == "response" and obj["request_index"] == 0 and obj["stream"] == 3


# --------------------------------------------------------------------------- fast JSON lines


def _slow(record: Record, view: View) -> bytes:
    return json_line(record_to_json(record, view)).encode()


def _records_of(path: Path, profile: list[str] | None = None) -> list[Record]:
    from mbmon.cli import make_annotator
    from mbmon.pipeline import Pipeline
    from mbmon.sources.pcapfile import read_capture

    return list(Pipeline(make_annotator(profile or [])).run(read_capture(path)))


def _views(records: list[Record]) -> list[View]:
    """A neutral view and the robot's view as the server of the first stream."""
    views = [View()]
    streams = [r.stream for r in records if r.stream is not None]
    if streams:
        views.append(View(robot=streams[0].server))
    return views


@pytest.mark.parametrize(
    ("name", "profile"),
    [("hrss_ptp.pcap", None), ("hrss_ptp.pcap", ["hrss"]), ("hrss_rtu.pcap", ["hrss"])],
)
def test_json_bytes_is_the_full_encoding_on_own_captures(
    name: str, profile: list[str] | None
) -> None:
    records = _records_of(REPO / "captures" / name, profile)
    assert any(r.notes for r in records) == bool(profile)
    for view in _views(records):
        for _ in range(2):  # the second pass reads every fixed part from the caches
            for record in records:
                assert record_json_bytes(record, view) == _slow(record, view)


def test_json_bytes_is_the_full_encoding_on_real_captures() -> None:
    if not REAL.is_dir():
        pytest.skip("../shared/captures/real absent")
    paths = sorted(p for p in REAL.iterdir() if p.suffix in (".pcap", ".pcapng"))
    assert paths
    for path in paths:
        records = _records_of(path)
        for view in _views(records):
            for record in records:
                assert record_json_bytes(record, view) == _slow(record, view), path.name


#: (request, response) PDUs: registers, bits trimmed by the request, PDU fields
#: (mask write, MEI objects with a quote in them), diagnostics, an exception
PAIRS = [
    ("03 01 90 00 02", "03 04 01 90 00 00"),
    ("02 01 2C 00 05", "02 01 13"),
    ("16 00 04 00 F2 00 25", "16 00 04 00 F2 00 25"),
    ("2B 0E 01 00", "2B 0E 01 01 00 00 01 00 03 41 22 43"),
    ("08 00 00 12 34", "08 00 00 12 34"),
    ("03 00 00 00 01", "83 02"),
]
_text = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=12)


@settings(max_examples=200, deadline=None)
@given(
    notes=st.lists(_text | st.sampled_from(['"', "\\", "\n", "\x00", "→", "\u2028"]), max_size=3),
    latency=st.none() | st.floats(0, 1e6, allow_nan=False),
    tid=st.none() | st.integers(0, 0xFFFF),
    crc_ok=st.sampled_from([None, True, False]),
    index=st.integers(0, 10**12),
    ts=st.floats(0, 4e9, allow_nan=False),
    request_index=st.none() | st.integers(0, 10**9),
    hexes=st.sampled_from(PAIRS),
    paired=st.booleans(),
    robot=st.sampled_from([None, "10.0.0.2", "10.0.0.1:50000"]),
)
def test_json_bytes_equals_the_full_encoding(
    notes: list[str],
    latency: float | None,
    tid: int | None,
    crc_ok: bool | None,
    index: int,
    ts: float,
    request_index: int | None,
    hexes: tuple[str, str],
    paired: bool,
    robot: str | None,
) -> None:
    """Whatever the record holds (notes needing JSON escapes, no tid, no latency,
    PDU fields), the line cut from cached parts is the full encoding."""
    view = View(robot=robot)
    req_pdu = decode_pdu(bytes.fromhex(hexes[0]), False)
    resp_pdu = decode_pdu(bytes.fromhex(hexes[1]), True, req_pdu if paired else None)
    req = Frame(ts, TCP, Direction.C2S, 1, tid, req_pdu, b"", crc_ok)
    resp = Frame(ts, TCP, Direction.S2C, 1, tid, resp_pdu, b"", crc_ok)
    kind = RecordKind.EXCEPTION if resp_pdu.fc != resp_pdu.raw[0] else RecordKind.RESPONSE
    records = [
        Record(index, ts, RecordKind.REQUEST, TCP, frame=req, notes=tuple(notes)),
        Record(
            index,
            ts,
            kind,
            TCP,
            frame=resp,
            request=req if paired else None,
            request_index=request_index,
            latency=latency if paired else None,
            notes=tuple(notes),
        ),
    ]
    for record in records * 2:
        assert record_json_bytes(record, view) == _slow(record, view)


def test_time_as_text_and_in_utf8_agree() -> None:
    """The JSON path's time (bytes) is the text time, whichever second was cached last."""
    from mbmon.format import _time_bytes

    stamps = [0.0, 1.5, 1700000000.000097, 1700000000.26, 1700000000.9999996, 1381967744.641998]
    for ts in stamps + stamps[::-1]:
        assert _time_bytes(ts) == format_time(ts).encode()
        assert format_time(ts) == _time_bytes(ts).decode()


def test_time_rounds_to_the_microsecond() -> None:
    from mbmon.format import format_time

    assert format_time(1700000000.26).endswith(".260000")
    assert format_time(1700000000.0000004).endswith(".000000")
    assert format_time(1700000000.9999996).endswith(".999999")


# --------------------------------------------------------------------------- time basis


IMPOSSIBLE_TIMES = [1e17, 1.8e19, 1.7e12, -1e12, float("nan"), float("inf"), -(2.0**63)]


def _pair(ts: float, stream: Stream = TCP) -> list[Record]:
    req = Frame(ts, stream, Direction.C2S, 1, 7 if stream is TCP else None,
                decode_pdu(bytes.fromhex("0300000001"), False), b"")  # fmt: skip
    resp = Frame(ts, stream, Direction.S2C, 1, 7 if stream is TCP else None,
                 decode_pdu(bytes.fromhex("03020007"), True, req.pdu), b"")  # fmt: skip
    return [
        Record(0, ts, RecordKind.REQUEST, stream, frame=req),
        Record(
            1,
            ts,
            RecordKind.RESPONSE,
            stream,
            frame=resp,
            request=req,
            request_index=0,
            latency=0.0125,
        ),
        Record(2, ts, RecordKind.EVENT, stream, event=Event(ts, stream, EventKind.CONNECT)),
    ]


@pytest.mark.parametrize("mode", ["a", "ad", "r", "e", "u", "ud"])
def test_every_time_mode_reaches_lines_and_json_alike(mode: str) -> None:
    """-t: the view's time format makes the line's time; the fast JSON path agrees with
    the general encoder; the JSON ``time`` stays epoch seconds."""
    import json

    from mbmon.timefmt import TimeFormat

    ts = 1714564805.123456
    view = View(time_format=TimeFormat(mode, origin=ts - 2.5))
    want = TimeFormat(mode, origin=ts - 2.5).text(ts)
    for record in _pair(ts) * 2:
        line = record_line(record, view)
        assert line.startswith(want + "  ")
        assert record_json_bytes(record, view) == json_line(record_to_json(record, view)).encode()
        obj = json.loads(record_json_bytes(record, view))
        assert obj["time"] == ts and obj["line"] == line


@pytest.mark.parametrize("ts", IMPOSSIBLE_TIMES)
def test_impossible_times_print(ts: float) -> None:
    """A timestamp no calendar shows prints (as epoch seconds), never raises."""
    import json

    from mbmon.timefmt import epoch_text

    for view in (View(), View(robot="10.0.0.2")):
        for record in _pair(ts) * 2:
            line = record_line(record, view)
            assert line.startswith(epoch_text(ts) + "  ")
            data = record_json_bytes(record, view)
            assert data == json_line(record_to_json(record, view)).encode()
            assert json.loads(data)["line"] == line
    assert format_time(ts) == epoch_text(ts)


def test_untimed_streams_show_record_numbers_and_no_latency() -> None:
    """A raw RTU dump has no capture times: ``#N`` instead of a time, no
    latency, and null ``time``/``latency_ms`` in valid JSON."""
    import json

    dump = Stream(0, Transport.RTU, "bus.bin", "bus.bin", timed=False)
    records = _pair(0.0, dump)
    lines = [record_line(r, View()) for r in records]
    assert [line.split("  ")[0] for line in lines] == ["#0", "#1", "#2"]
    assert not any("00:00:00" in line or " ms)" in line for line in lines)
    for record in records:
        obj = json.loads(record_json_bytes(record, View()))
        assert obj["time"] is None and obj["latency_ms"] is None
        assert obj == json.loads(json_line(record_to_json(record, View())))
    timed = record_line(_pair(0.0, BUS)[1], View())
    assert "(12.5 ms)" in timed  # the same records on a timed bus: latency shown


def test_json_bytes_is_the_full_encoding_on_a_realistic_capture(tmp_path: Path) -> None:
    """A cell's capture as bench/realistic.py builds it (connections captured
    mid-stream, register values that change every poll, writes, exceptions):
    nearly every answer is a PDU never seen before, so its fixed JSON parts are
    made value by value (jsonfmt._parts_from_json), not cut from a full encoding."""
    import random
    import sys

    sys.path.insert(0, str(REPO / "bench"))
    try:
        import realistic
    finally:
        sys.path.remove(str(REPO / "bench"))
    path = tmp_path / "cell.pcap"
    adus = realistic.polling_adus(random.Random(5), 5, 1500)
    realistic.build(path, adus, 5, 2, "mixed", seed=5)
    records = _records_of(path)
    assert sum(r.kind is RecordKind.RESPONSE for r in records) > 1400
    for view in _views(records):
        for record in records:
            assert record_json_bytes(record, view) == _slow(record, view)


def test_parts_are_made_on_a_pdus_second_sighting_not_its_first() -> None:
    """An answer with values never seen before is encoded whole (making its parts
    would cost more, and on a cell's capture it never comes again); the second
    record with the same PDU makes the parts, the third uses them. Each line is the
    full encoding all the same. A fresh view starts with empty caches: the test does
    not depend on what other tests encoded before it."""
    view = View()
    first = _pair(1.0)
    resp = first[1]
    frame = resp.frame
    req = first[0].frame
    assert frame is not None and req is not None
    # another answer to the same read makes the heads and the read's template
    values = decode_pdu(bytes.fromhex("03020008"), True, req.pdu)
    other = Frame(0.5, TCP, Direction.S2C, 1, 7, values, b"")
    answer = Record(9, 0.5, RecordKind.RESPONSE, TCP, frame=other, request=req, request_index=0)
    for record in (first[0], answer):
        assert record_json_bytes(record, view) == _slow(record, view)
    key = (id(frame.pdu), id(first[0].frame.pdu), resp.kind, frame.unit, frame.crc_ok)  # type: ignore[union-attr]
    for sighting in (1, 2, 3):
        record = Record(
            10 + sighting, 1.0 + sighting, RecordKind.RESPONSE, resp.stream, frame=frame,
            request=resp.request, request_index=0, latency=0.001 * sighting,
        )  # fmt: skip
        assert record_json_bytes(record, view) == _slow(record, view)
        assert (key in view.json_cache.parts) is (sighting >= 2), sighting
    assert len(view.json_cache.seen_once) <= SEEN_ONCE_SIZE


#: reads and answers whose values a hypothesis draws: registers (03, 04, 17; more
#: than the 16 values a note shows), bits (01, 02; more than the 64 it shows)
READS = [
    ("03 00 00 00 0A", 3, 10, False),
    ("04 01 00 00 14", 4, 20, False),
    ("17 00 00 00 03 00 10 00 01 02 00 05", 0x17, 3, False),
    ("01 00 00 00 05", 1, 5, True),
    ("02 00 10 00 48", 2, 72, True),
]


def _answer(fc: int, count: int, bits: bool, values: list[int]) -> bytes:
    if bits:
        data = bytearray((count + 7) // 8)
        for i, v in enumerate(values[:count]):
            data[i >> 3] |= (v & 1) << (i & 7)
        return bytes([fc, len(data)]) + bytes(data)
    body = b"".join((v & 0xFFFF).to_bytes(2, "big") for v in values[:count])
    return bytes([fc, len(body)]) + body


@settings(max_examples=60, deadline=None)
@given(
    read=st.sampled_from(READS),
    polls=st.lists(
        st.lists(st.integers(0, 0xFFFF), min_size=72, max_size=72), min_size=2, max_size=6
    ),
    crc_ok=st.sampled_from([None, True, False]),
    notes=st.lists(st.sampled_from(["", '"q"', "→ A1 = 90.000°"]), max_size=2),
    robot=st.sampled_from([None, "10.0.0.2"]),
)
def test_answers_with_new_values_are_filled_from_the_read_template(
    read: tuple[str, int, int, bool],
    polls: list[list[int]],
    crc_ok: bool | None,
    notes: list[str],
    robot: str | None,
) -> None:
    """A robot's position changes every poll, so its answers are PDUs never seen
    before: after the first, their lines come from the request's template (no JSON
    object, no note made per answer) and are the full encoding all the same, also
    for a malformed answer of the template's length in between."""
    import mbmon.jsonfmt as fmt

    view = View(robot=robot)
    req_hex, fc, count, bits = read
    req = Frame(1.0, TCP, Direction.C2S, 1, 7, decode_pdu(bytes.fromhex(req_hex), False), b"")
    answers = [_answer(fc, count, bits, values) for values in polls]
    bad = bytes([answers[0][0], answers[0][1] + 1]) + answers[0][2:]  # wrong byte count
    calls = 0
    real = fmt.record_to_json

    def counting(*args: object, **kwargs: object) -> object:
        nonlocal calls
        calls += 1
        return real(*args, **kwargs)  # type: ignore[arg-type]

    for i, raw in enumerate([*answers[:1], bad, *answers[1:]]):
        pdu = decode_pdu(raw, True, req.pdu)
        frame = Frame(1.0 + i, TCP, Direction.S2C, 1, 7, pdu, b"", crc_ok)
        record = Record(
            i, 1.0 + i, RecordKind.RESPONSE, TCP, frame=frame, request=req, request_index=0,
            latency=0.001 * i, notes=tuple(notes),
        )  # fmt: skip
        expected = _slow(record, view)
        fmt.record_to_json = counting  # type: ignore[assignment]
        try:
            calls = 0
            assert record_json_bytes(record, view) == expected
        finally:
            fmt.record_to_json = real
        if i >= 2:
            assert pdu.malformed is None
            assert calls == 0, "a new answer to a templated read took the general path"
    assert decode_pdu(bad, True, req.pdu).malformed


#: (PDU hex, response?, generic note): function codes shown by their sub-function's or
#: MEI type's name, and 0x17 with the values it writes (as its JSON has them).
NAMED_NOTES = [
    ("17 0000 0002 0010 0002 04 000A 000B", False,
     "Read/Write Multiple Registers 0..1, write 16..17 = 10, 11"),
    ("17 04 0001 0002", True, "Read/Write Multiple Registers = 1, 2"),
    ("08 0004 0000", False, "Diagnostics sub-function 4 Force Listen Only Mode = 0"),
    ("08 0001 FF00", False, "Diagnostics sub-function 1 Restart Communications Option = 65280"),
    ("08 000B 0000", False, "Diagnostics sub-function 11 Return Bus Message Count = 0"),
    ("08 0063 0000", False, "Diagnostics sub-function 99 = 0"),  # reserved: no name
    ("2B 0E 01 00", False, "Read Device Identification basic, object 0 VendorName"),
    ("2B 0E 04 81", False, "Read Device Identification one object, object 129"),
    ("2B 0E 01 01 00 00 02 00 05 484957494E 01 02 5831", True,
     "Read Device Identification basic: VendorName='HIWIN', ProductCode='X1'"),
    ("2B 0D 0102", False, "CANopen General Reference"),
    ("2B 0C 0102", False, "Encapsulated Interface Transport MEI type 0x0C"),
]  # fmt: skip


@pytest.mark.parametrize(("hexpdu", "response", "note"), NAMED_NOTES)
def test_notes_name_sub_functions_mei_types_and_show_what_0x17_writes(
    hexpdu: str, response: bool, note: str
) -> None:
    assert generic_note(decode_pdu(bytes.fromhex(hexpdu), response)) == note


def test_json_caches_belong_to_their_view_and_stay_bounded_in_bytes() -> None:
    """Each view keeps its own JSON parts (two runs in one process share nothing),
    and a view's parts never hold much more than their byte bound, whatever the
    traffic: here long register answers, each seen twice so that its parts are made."""
    from mbmon.jsoncache import CACHE_BYTES

    view, other = View(), View()
    req = Frame(1.0, TCP, Direction.C2S, 1, 7, decode_pdu(bytes.fromhex("0300000078"), False), b"")
    biggest = 0
    for i in range(1000):
        values = [(i * 7 + k) & 0xFFFF for k in range(120)]
        pdu = decode_pdu(_answer(3, 120, False, values), True, req.pdu)
        frame = Frame(1.0 + i, TCP, Direction.S2C, 1, 7, pdu, b"")
        for n in range(2):
            record = Record(
                2 * i + n, 1.0 + i, RecordKind.RESPONSE, TCP, frame=frame, request=req,
                request_index=0, latency=0.001,
            )  # fmt: skip
            assert record_json_bytes(record, view) == _slow(record, view)
        biggest = max(biggest, view.json_cache.held)
    assert view.json_cache.parts and not other.json_cache.parts
    assert CACHE_BYTES < biggest < CACHE_BYTES + 4096  # emptied once past the bound
