"""Log format 3's protobuf messages (``mbmon.io.mcap.proto``): every ``/modbus/frames``
and ``/modbus/raw`` object of a format-2 log goes to protobuf and back member for
member, in order, with JSON bytes identical to the stored ones; google.protobuf, given
only the FileDescriptorSet the log's schema records carry, reads our bytes as our
decoder does (an independent oracle); byte tables pin the wire format; damaged or
hostile bytes give :class:`ProtoError`, never another exception."""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.io.mcap import proto
from mbmon.io.mcap.reader import McapLog

REPO = Path(__file__).resolve().parents[2]
CAPTURES = ["demo.pcap", "hrss_ptp.pcap", "sim_functions.pcap", "sim_exceptions.pcap"]


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), ensure_ascii=False).encode()


def _canonical(obj: dict[str, Any]) -> dict[str, Any]:
    """``obj``'s members in the order the writers make (the read --json object's)."""
    ordered = {k: obj[k] for k in proto._FRAME_ORDER if k in obj}
    ordered.update({k: v for k, v in obj.items() if k not in ordered})
    return ordered


def _oracle() -> dict[str, Any]:
    pb = pytest.importorskip("google.protobuf", reason="protobuf (a test extra) not installed")
    del pb
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(proto.descriptor_set())
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return {
        name: message_factory.GetMessageClass(pool.FindMessageTypeByName(name))
        for name in (proto.FRAME_SCHEMA, proto.RAW_SCHEMA)
    }


def _oracle_object(msg: Any) -> dict[str, Any]:
    """What google.protobuf read, as our decoder gives it before the JSON shape: every
    set field by name (repeated ones as lists)."""
    out: dict[str, Any] = {}
    for fd, value in msg.ListFields():
        out[fd.name] = list(value) if fd.is_repeated else value
    return out


@pytest.fixture(scope="module")
def stored(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, bytes]]:
    """(topic, payload) of every frames and raw message of format-3 logs written now
    from the project's captures: as stored (protobuf), and the format-2 JSON the
    readers give of it."""
    from logmutate import run_command

    out: list[tuple[str, bytes]] = []
    folder = tmp_path_factory.mktemp("logs")
    for name in CAPTURES:
        src = REPO / "captures" / name
        if not src.exists():
            continue
        log = folder / f"{name}.mcap"
        extra = ["--profile", "hrss"] if name.startswith("hrss") else []
        status, _, err, escape = run_command(
            ["read", str(src), *extra, "-q", "-w", str(log)], budget=None
        )
        assert escape is None and status == 0, err
        with McapLog(log) as mlog:
            for m in mlog.messages(["/modbus/frames", "/modbus/raw"]):
                out.append((m.topic, m.raw))
                out.append((m.topic, _dumps(m.json())))  # the format-2 object of it
    if not out:
        pytest.skip("no capture in captures/")
    return out


def test_every_stored_message_round_trips(stored: list[tuple[str, bytes]]) -> None:
    oracle = _oracle()
    for topic, raw in stored:
        frames = topic == "/modbus/frames"
        if not raw.startswith(b"{"):  # as a format-3 log stores it: protobuf
            obj = proto.decode_frame(raw) if frames else proto.decode_raw(raw)
            assert (proto.encode_frame(obj) if frames else proto.encode_raw(obj)) == raw
            continue
        obj = json.loads(raw)
        data = proto.encode_frame(obj) if frames else proto.encode_raw(obj)
        back = proto.decode_frame(data) if frames else proto.decode_raw(data)
        assert back == obj and list(back) == list(obj), (raw, back)
        assert _dumps(back) == raw
        theirs = oracle[proto.FRAME_SCHEMA if frames else proto.RAW_SCHEMA].FromString(data)
        ours = proto._decode(proto.messages()[theirs.DESCRIPTOR.full_name], data)
        assert _oracle_object(theirs) == ours


def test_the_descriptor_is_the_proto_files() -> None:
    oracle = _oracle()
    frame = oracle[proto.FRAME_SCHEMA].DESCRIPTOR
    fields = {f.name: (f.number, f.type) for f in frame.fields}
    assert fields["values"] == (14, frame.fields_by_name["values"].TYPE_INT64)
    assert frame.fields_by_name["values"].is_packed
    assert [f.name for f in frame.fields] == [f.name for f in proto.messages()["modbus.Frame"]]
    assert frame.fields_by_name["time"].has_presence


# one request and its answer, as read --json makes them (format 2: no line, no nulls)
REQUEST = {
    "index": 2, "time": 1700000000.000679, "stream": 0, "src": "10.0.1.2:40000",
    "dst": "10.0.0.1:502", "transport": "tcp", "tid": 22846, "unit": 1, "fc": 3,
    "kind": "request", "address": 988, "count": 2, "pdu": "03 03 DC 00 02",
    "notes": ["Read Holding Registers 988..989"],
}  # fmt: skip


def test_frame_bytes() -> None:
    data = proto.encode_frame(REQUEST)
    assert data == (
        b"\x08\x02"  # index 2
        + b"\x11" + struct.pack("<d", 1700000000.000679)  # time, a double
        + b"\x18\x00"  # stream 0
        + b"\x22\x0e10.0.1.2:40000" + b"\x2a\x0c10.0.0.1:502" + b"\x32\x03tcp"
        + b"\x38\xbe\xb2\x01"  # tid 22846
        + b"\x40\x01\x48\x03" + b"\x52\x07request"
        + b"\x60\xdc\x07\x68\x02"  # address 988, count 2
        + b"\x7a\x05\x03\x03\xdc\x00\x02"  # pdu as bytes
        + b"\x82\x01\x1fRead Holding Registers 988..989"  # notes, field 16
    )  # fmt: skip
    assert proto.decode_frame(data) == REQUEST


def test_what_a_field_cannot_hold_goes_to_extra() -> None:
    obj = {
        **REQUEST, "values": [], "pdu": "03 03 dc", "crc_ok": None, "unit": True,
        "fields": {"sub_function": 0, "data": "00 00"}, "latency_ms": 5,
        "notes": ["caf\u00e9", "\ud800 lone"],
    }  # fmt: skip
    obj = _canonical(obj)
    data = proto.encode_frame(obj)
    back = proto.decode_frame(data)
    assert back == obj
    assert list(back) == list(obj)
    assert type(back["unit"]) is bool and type(back["latency_ms"]) is int
    extra = json.loads(proto._decode(proto.messages()["modbus.Frame"], data)["extra"])
    assert set(extra) == {"values", "pdu", "crc_ok", "unit", "fields", "latency_ms", "notes"}


def test_raw_chunk_and_event() -> None:
    chunk = {
        "type": "chunk", "stream": 0, "transport": "tcp", "client": "10.0.1.2:40000",
        "server": "10.0.0.1:502", "direction": "c2s", "ts": 1700000000.000679,
        "data": "WT4AAAAGAQED3AAj",
    }  # fmt: skip
    event = {
        "type": "event", "stream": 1, "transport": "tcp", "client": "a", "server": "b",
        "ts": 1700000000.5, "direction": None, "data": "", "event": "connect", "info": {},
    }  # fmt: skip
    untimed = {k: v for k, v in chunk.items() if k != "direction" and k != "ts" and k != "data"}
    untimed.update(timed=False, direction="bus", ts=0.0, data="not base64!")
    for obj in (chunk, event, untimed):
        back = proto.decode_raw(proto.encode_raw(obj))
        assert back == obj and list(back) == list(obj)
    assert b"Y>\x00\x00\x00\x06\x01\x01\x03\xdc\x00#" in proto.encode_raw(chunk)


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (b"\x08", "varint runs past"),
        (b"\x11\x00\x00", "64-bit field runs past"),
        (b"\x22\x05ab", "length-delimited field runs past"),
        (b"\x22\x02\xff\xfe", "not UTF-8"),
        (b"\x10\x01", "wire type 0, not 1"),  # time as a varint
        (b"\xf2\x01\x02[]", "extra: not a JSON object"),
        (b"\xf2\x01\x01{", "extra: not JSON"),
        (b"\x08" + b"\xff" * 11, "longer than 10 bytes"),
        (b"\x0b", "wire type 3"),
        (b"\x00\x00", "field number 0"),
    ],
)
def test_damaged_messages(data: bytes, why: str) -> None:
    with pytest.raises(proto.ProtoError, match=why):
        proto.decode_frame(data)


def test_unknown_fields_are_passed_over() -> None:
    data = b"\xc8\x3e\x05" + b"\xd5\x3e\x00\x00\x00\x00" + proto.encode_frame(REQUEST)
    assert proto.decode_frame(data) == REQUEST


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=80))
def test_random_bytes_decode_or_give_proto_error(data: bytes) -> None:
    for decode in (proto.decode_frame, proto.decode_raw):
        try:
            obj = decode(data)
        except proto.ProtoError:
            continue
        assert isinstance(obj, dict)
        json.dumps(obj)  # whatever it gives is a JSON object


_json = st.recursive(
    st.none() | st.booleans() | st.integers(-(1 << 70), 1 << 70)
    | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3)
    ),
    max_leaves=6,
)  # fmt: skip
_keys = st.sampled_from([*proto._FRAME_ORDER, "fields", "extra", "event"])


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(_keys, _json, max_size=8))
def test_any_object_round_trips(obj: dict[str, Any]) -> None:
    ordered = _canonical(obj)
    back = proto.decode_frame(proto.encode_frame(ordered))
    assert back == ordered and list(back) == list(ordered)
