"""MBAP stream decoder: byte tables, chunking, garbage and resynchronisation."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mbmon.model import Direction, Frame, Kind, Noise, Stream, Transport
from mbmon.protocol.mbap import NOISE_CAP, MbapDecoder, encode_adu

STREAM = Stream(0, Transport.TCP, "10.0.0.2:50000", "10.0.0.1:502")


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# Spec examples (Modbus Application Protocol v1.1b3 / Messaging on TCP/IP), unit 0x11.
REQ_03 = h("00 01 00 00 00 06 11 03 00 6B 00 03")  # read 3 holding registers at 0x006B
RESP_03 = h("00 01 00 00 00 09 11 03 06 02 2B 00 00 00 64")  # 0x022B, 0x0000, 0x0064
EXC_03 = h("00 02 00 00 00 03 11 83 02")  # illegal data address
REQ_01 = h("00 03 00 00 00 06 11 01 00 13 00 13")  # read 19 coils at 0x13
REQ_10 = h("00 04 00 00 00 0B 11 10 00 01 00 02 04 00 0A 01 02")  # write 2 regs at 1
REQ_05 = h("00 05 00 00 00 06 11 05 00 AC FF 00")  # coil 0xAC on


def decode(data: bytes, direction: Direction = Direction.C2S) -> list[Frame | Noise]:
    dec = MbapDecoder(STREAM, direction)
    return dec.feed(data, 1.0) + dec.flush(2.0)


def frames(items: list[Frame | Noise]) -> list[Frame]:
    return [x for x in items if isinstance(x, Frame)]


def noises(items: list[Frame | Noise]) -> list[Noise]:
    return [x for x in items if isinstance(x, Noise)]


def key(f: Frame) -> tuple[object, ...]:
    return (f.unit, f.tid, f.direction, f.raw, f.pdu)


def test_one_request() -> None:
    out = decode(REQ_03)
    assert len(out) == 1
    f = out[0]
    assert isinstance(f, Frame)
    assert (f.ts, f.stream, f.direction) == (1.0, STREAM, Direction.C2S)
    assert (f.tid, f.unit, f.crc_ok) == (1, 0x11, None)
    assert f.raw == REQ_03
    assert f.pdu.raw == h("03 00 6B 00 03")
    assert (f.pdu.kind, f.pdu.fc, f.pdu.address, f.pdu.count) == (Kind.REQUEST, 3, 0x6B, 3)


def test_one_response() -> None:
    [f] = decode(RESP_03, Direction.S2C)
    assert isinstance(f, Frame)
    assert f.direction is Direction.S2C
    assert (f.tid, f.unit) == (1, 0x11)
    assert f.pdu.kind is Kind.RESPONSE
    assert f.pdu.values == (0x022B, 0x0000, 0x0064)


def test_exception_response() -> None:
    [f] = decode(EXC_03, Direction.S2C)
    assert isinstance(f, Frame)
    assert f.tid == 2
    assert (f.pdu.kind, f.pdu.fc, f.pdu.exception_code) == (Kind.EXCEPTION, 3, 2)
    assert f.pdu.raw == h("83 02")


def test_several_adus_in_one_chunk() -> None:
    data = REQ_03 + REQ_01 + REQ_10 + REQ_05
    out = decode(data)
    assert noises(out) == []
    assert [f.raw for f in frames(out)] == [REQ_03, REQ_01, REQ_10, REQ_05]
    assert [f.tid for f in frames(out)] == [1, 3, 4, 5]
    assert frames(out)[2].pdu.values == (0x000A, 0x0102)


def test_split_at_every_offset_gives_identical_frames() -> None:
    data = REQ_03 + REQ_01 + REQ_10 + REQ_05
    whole = [key(f) for f in frames(decode(data))]
    for cut in range(len(data) + 1):
        dec = MbapDecoder(STREAM, Direction.C2S)
        out = dec.feed(data[:cut], 1.0) + dec.feed(data[cut:], 2.0) + dec.flush(3.0)
        assert noises(out) == [], cut
        assert [key(f) for f in frames(out)] == whole, cut


def test_byte_by_byte_and_ts_of_completing_chunk() -> None:
    data = REQ_03 + RESP_03[:0] + REQ_01
    dec = MbapDecoder(STREAM, Direction.C2S)
    out: list[Frame | Noise] = []
    for i, b in enumerate(data):
        out += dec.feed(bytes([b]), float(i))
    assert [f.raw for f in frames(out)] == [REQ_03, REQ_01]
    # each frame carries the time of the chunk holding its last byte
    assert [f.ts for f in frames(out)] == [float(len(REQ_03) - 1), float(len(data) - 1)]


def test_split_inside_header_timestamp() -> None:
    dec = MbapDecoder(STREAM, Direction.C2S)
    assert dec.feed(REQ_03[:3], 10.0) == []
    assert dec.feed(REQ_03[3:6], 11.0) == []
    [f] = dec.feed(REQ_03[6:] + REQ_01[:8], 12.5)
    assert isinstance(f, Frame)
    assert f.ts == 12.5
    [g] = dec.feed(REQ_01[8:], 13.0)
    assert isinstance(g, Frame)
    assert (g.raw, g.ts) == (REQ_01, 13.0)


def test_garbage_prefix_is_one_noise() -> None:
    garbage = h("DE AD BE EF 12 34 56")
    out = decode(garbage + REQ_03 + REQ_01)
    assert len(out) == 3
    n = out[0]
    assert isinstance(n, Noise)
    assert n.raw == garbage
    assert n.reason == "bad MBAP header (protocol id 0xBEEF)"
    assert (n.stream, n.direction) == (STREAM, Direction.C2S)
    assert [f.raw for f in frames(out)] == [REQ_03, REQ_01]


def test_protocol_id_not_zero() -> None:
    # From the Digital Bond capture: a header with protocol id 0x0010.
    bad = h("00 01 00 10 00 06 0A 01 00 01 00 03")
    out = decode(REQ_03 + bad + REQ_01)
    assert [type(x) for x in out] == [Frame, Noise, Frame]
    n = out[1]
    assert isinstance(n, Noise)
    assert n.raw == bad
    assert n.reason == "bad MBAP header (protocol id 0x0010)"


def test_bad_length_0x8804_is_one_noise_run() -> None:
    # The Digital Bond client stream: back-to-back headers with length 0x8804.
    pattern = h("00 01 00 00 88 04 05 07 08 09 10")
    garbage = pattern * 41
    out = decode(REQ_03 + garbage + REQ_01)
    assert [type(x) for x in out] == [Frame, Noise, Frame]
    n = out[1]
    assert isinstance(n, Noise)
    assert n.raw == garbage
    assert n.reason == "bad MBAP length 34820"
    assert frames(out)[1].raw == REQ_01


def test_length_below_two_is_garbage() -> None:
    bad = h("00 07 00 00 00 01 11")  # length 1: unit id without function code
    out = decode(bad + REQ_03)
    assert [type(x) for x in out] == [Noise, Frame]
    assert out[0].raw == bad
    assert out[0].reason == "bad MBAP length 1"  # type: ignore[union-attr]


def test_max_length_is_configurable() -> None:
    pdu = bytes([0x03, 0xFA]) + bytes(250)  # 252-byte PDU -> MBAP length 253
    adu = encode_adu(9, 1, pdu)
    assert frames(decode(adu, Direction.S2C))[0].raw == adu
    dec = MbapDecoder(STREAM, Direction.S2C, max_length=200)
    out = dec.feed(adu, 1.0) + dec.flush(2.0)
    assert frames(out) == []
    assert noises(out)[0].reason == "bad MBAP length 253"


def test_mid_stream_start_resyncs() -> None:
    # The capture starts inside a response: its last 7 bytes (register data that
    # even contains a "00 00 00 64" look-alike header) precede whole ADUs.
    tail = RESP_03[-7:]  # 06 02 2B 00 00 00 64
    later = h("00 07 00 00 00 09 11 03 06 00 01 00 02 00 03") + RESP_03
    out = decode(tail + later, Direction.S2C)
    assert [type(x) for x in out] == [Noise, Frame, Frame]
    assert out[0].raw == tail
    assert [f.tid for f in frames(out)] == [7, 1]


def test_short_length_with_trailing_bytes_resyncs() -> None:
    # Digital Bond part 1: a 0x2A response whose MBAP length (5) is 3 bytes
    # shorter than the 14 bytes sent; the 3 trailing bytes precede the next ADU.
    sent = h("00 01 00 00 00 05 0A 2A 0E 04 01 01 01 23")
    nxt = h("00 01 00 00 00 04 0A 81 06 00")  # exception with one trailing byte
    out = decode(sent + nxt + sent + nxt, Direction.S2C)
    assert [type(x) for x in out] == [Frame, Noise, Frame, Frame, Noise, Frame]
    assert out[0].raw == sent[:11]
    assert out[1].raw == h("01 01 23")
    assert out[2].raw == nxt
    assert out[2].pdu.kind is Kind.EXCEPTION  # type: ignore[union-attr]
    # the same bytes one per chunk give the same frames
    dec = MbapDecoder(STREAM, Direction.S2C)
    parts: list[Frame | Noise] = []
    for b in sent + nxt + sent + nxt:
        parts += dec.feed(bytes([b]), 1.0)
    parts += dec.flush(2.0)
    assert [key(f) for f in frames(parts)] == [key(f) for f in frames(out)]


def test_resync_skips_implausible_candidates() -> None:
    # Inside a noise run, "FF FF 00 00 00 03 11 00" has the form of a header
    # but function code 0 is implausible, and "77 FF 00 00 00 0C 11 03 ..."
    # claims 11 PDU bytes for a 5-byte 0x03 request: both are skipped.
    garbage = (
        h("DE AD BE EF")
        + h("FF FF 00 00 00 03 11 00 AA")
        + h("77 FF 00 00 00 0C 11 03 01 02 03 04 05 06 07 08 09 0A 0B")
    )
    out = decode(garbage + REQ_03)
    assert [type(x) for x in out] == [Noise, Frame]
    assert out[0].raw == garbage
    assert out[0].reason == "bad MBAP header (protocol id 0xBEEF)"  # type: ignore[union-attr]
    assert out[1].raw == REQ_03
    # Outside a noise run the same header form is taken (a sweep may start at fc 0).
    [f] = frames(decode(h("00 00 00 00 00 02 11 00")))
    assert (f.unit, f.pdu.fc) == (0x11, 0)


def test_resync_accepts_a_few_trailing_bytes() -> None:
    # A plausible ADU with up to 4 trailing bytes after a predictable PDU is
    # still a resync point (devices that pad), 5 or more is not.
    pad4 = h("00 09 00 00 00 0A 11 03 00 6B 00 03 EE EE EE EE")
    pad5 = h("00 0A 00 00 00 0B 11 03 00 6B 00 03 EE EE EE EE EE")
    out = decode(h("DE AD BE EF") + pad4)
    assert [type(x) for x in out] == [Noise, Frame]
    assert out[1].raw == pad4
    out = decode(h("DE AD BE EF") + pad5 + REQ_03)
    assert [type(x) for x in out] == [Noise, Frame]
    assert out[0].raw == h("DE AD BE EF") + pad5


def test_flush_reports_truncated_tail() -> None:
    dec = MbapDecoder(STREAM, Direction.C2S)
    out = dec.feed(REQ_03 + REQ_01[:5], 1.0)
    assert [f.raw for f in frames(out)] == [REQ_03]
    [n] = dec.flush(5.0)
    assert isinstance(n, Noise)
    assert (n.raw, n.reason, n.ts) == (
        REQ_01[:5],
        "truncated ADU at end of stream",
        1.0,
    )  # when it arrived
    assert dec.flush(6.0) == []


def test_reset_after_gap_discards_and_resumes() -> None:
    dec = MbapDecoder(STREAM, Direction.C2S)
    assert frames(dec.feed(REQ_03 + REQ_10[:9], 1.0))[0].raw == REQ_03
    [n] = dec.reset(2.0)
    assert (n.raw, n.reason, n.ts) == (REQ_10[:9], "discarded after gap", 1.0)  # when it arrived
    assert dec.reset(2.5) == []
    [f] = dec.feed(REQ_05, 3.0)
    assert isinstance(f, Frame)
    assert f.raw == REQ_05


def test_reset_reports_pending_noise_run() -> None:
    dec = MbapDecoder(STREAM, Direction.C2S)
    assert dec.feed(h("01 02 03 04 05 06 07 08"), 1.0) == []  # noise run, not yet ended
    out = dec.reset(2.0)
    assert sum(len(x.raw) for x in out) == 8
    assert out[0].reason == "bad MBAP header (protocol id 0x0304)"


def test_noise_run_spanning_chunks_is_reported_once() -> None:
    garbage = bytes(range(0x41, 0x41 + 40))
    dec = MbapDecoder(STREAM, Direction.C2S)
    out: list[Frame | Noise] = []
    for i in range(0, len(garbage), 7):
        out += dec.feed(garbage[i : i + 7], float(i))
    out += dec.feed(REQ_03, 99.0)
    assert [type(x) for x in out] == [Noise, Frame]
    assert out[0].raw == garbage
    assert out[0].ts == 0.0  # when the run began


def test_encode_adu() -> None:
    assert encode_adu(1, 0x11, h("03 00 6B 00 03")) == REQ_03
    assert encode_adu(0xFFFF, 0, b"\x11")[:6] == h("FF FF 00 00 00 02")
    with pytest.raises(ValueError):
        encode_adu(0x10000, 1, b"\x03")
    with pytest.raises(ValueError):
        encode_adu(1, 256, b"\x03")


def test_bus_direction_rejected() -> None:
    with pytest.raises(ValueError):
        MbapDecoder(STREAM, Direction.BUS)


def test_long_noise_run_is_split_at_the_cap() -> None:
    garbage = b"\xff" * (NOISE_CAP + 1000)
    dec = MbapDecoder(STREAM, Direction.S2C)
    out = dec.feed(garbage[:5000], 1.0) + dec.feed(garbage[5000:] + RESP_03, 2.0)
    assert [type(x) for x in out] == [Noise, Noise, Frame]
    assert [len(x.raw) for x in out[:2]] == [NOISE_CAP, 1000]
    assert out[2].raw == RESP_03


# --------------------------------------------------------------------------- split_clean

_ADUS = st.builds(
    lambda tid, unit, pdu: encode_adu(tid, unit, pdu),
    st.integers(0, 0xFFFF),
    st.integers(0, 0xFF),
    st.binary(min_size=1, max_size=253),
)


def test_split_clean_byte_table() -> None:
    dec = MbapDecoder(STREAM, Direction.C2S)
    assert dec.split_clean(REQ_03, 1.0) == [REQ_03]
    assert dec.split_clean(REQ_03 + REQ_10, 1.0) == [REQ_03, REQ_10]
    assert dec.split_clean(REQ_03[:7], 1.0) is None  # partial: the decoder waits
    assert dec.split_clean(REQ_03 + REQ_10[:3], 1.0) is None
    assert dec.split_clean(h("00 01 00 01 00 06 11 03 00 6B 00 03"), 1.0) is None  # proto 1
    long = encode_adu(1, 1, bytes([0x5A]) + bytes(253))  # length 255: malformed, not clean
    assert dec.split_clean(long, 1.0) is None
    assert dec.feed(REQ_03[:5], 1.0) == []  # something buffered: feed decides
    assert dec.split_clean(REQ_10, 2.0) is None


def test_feed_adus_byte_table() -> None:
    """What the proxy does with a read split_clean declined: the ADUs' bytes up to
    the first noise, and that noise."""
    dec = MbapDecoder(STREAM, Direction.C2S)
    assert dec.feed_adus(REQ_03[:7], 1.0) == ([], None)  # half an ADU: nothing yet
    assert dec.feed_adus(REQ_03[7:] + REQ_10, 2.0) == ([REQ_03, REQ_10], None)
    raws, noise = MbapDecoder(STREAM, Direction.C2S).feed_adus(REQ_03 + b"GET / HTTP/1.1\r\n", 3.0)
    assert raws == [REQ_03] and noise is None  # garbage held back: feed decides later
    dec = MbapDecoder(STREAM, Direction.C2S)
    raws, noise = dec.feed_adus(h("00 01 00 01 00 06 11 03 00 6B 00 03") + REQ_03, 4.0)
    assert isinstance(noise, Noise) and noise.raw and raws == []


@given(st.lists(_ADUS, min_size=1, max_size=6))
def test_split_clean_takes_every_run_of_whole_clean_adus(adus: list[bytes]) -> None:
    dec = MbapDecoder(STREAM, Direction.S2C)
    assert dec.split_clean(b"".join(adus), 1.0) == adus
    assert dec.buffered == 0


@given(
    st.one_of(st.binary(max_size=80), st.lists(_ADUS, max_size=3).map(b"".join)),
    st.binary(max_size=12),
)
def test_split_clean_agrees_with_feed(head: bytes, tail: bytes) -> None:
    """Whatever split_clean takes, feed frames the same bytes as the same ADUs and
    keeps nothing back; what it declines leaves the decoder as it was."""
    data = head + tail
    for direction in (Direction.C2S, Direction.S2C):
        fast = MbapDecoder(STREAM, direction)
        slow = MbapDecoder(STREAM, direction)
        raws = fast.split_clean(data, 1.0)
        items = slow.feed(data, 1.0)
        if raws is not None:
            assert [type(x) for x in items] == [Frame] * len(raws)
            assert [x.raw for x in items] == raws
            assert slow.buffered == 0
        assert fast.buffered == 0
        assert [key(f) for f in frames(fast.feed(data, 1.0))] == [key(f) for f in frames(items)]
