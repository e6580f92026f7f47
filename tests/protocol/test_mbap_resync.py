"""MBAP resynchronisation needs corroboration; length 255; one noise run, one record;
the decoder's tick (time reaches every layer)."""

from __future__ import annotations

import ssl

from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.model import Direction, Frame, Kind, Noise, Stream, Transport
from mbmon.protocol.mbap import MbapDecoder, encode_adu

STREAM = Stream(0, Transport.TCP, "10.0.0.2:50000", "10.0.0.1:502")
REQ_03 = bytes.fromhex("00 01 00 00 00 06 11 03 00 6B 00 03")

#: an HTTP request to port 502 with an MBAP look-alike inside
HTTP = (
    b"GET / HTTP/1.1\r\nHost: x\r\nX-Pad: "
    + bytes.fromhex("00 00 00 00 00 04 07 41 42 43")
    + b"\r\n\r\n"
)

#: A TLS 1.3 ClientHello (Python's ssl module, SNI plc.example), as a client sends it
#: to port 502 by mistake: extension headers and padding are full of 00 00 pairs.
CLIENT_HELLO = bytes.fromhex(
    "1603010200010001fc0303603f3e0d9329893548bc3b29134ed96757db0a4632d719bbb2b71cf943"
    "5c0fb920aefd564541853a54a893f5e0270c5f68e00bdc19c8e6384c49df00a935fa243a00241302"
    "13031301c02cc030c02bc02fcca9cca8c024c028c023c027009f009e006b006700ff0100018f0000"
    "0010000e00000b706c632e6578616d706c65000b000403000102000a00160014001d0017001e0019"
    "001801000101010201030104002300000016000000170000000d002a002804030503060308070808"
    "0809080a080b080408050806040105010601030303010302040205020602002b0005040304030300"
    "2d00020101003300260024001d0020e7a5da170d67707ea6f9e781d2336930d33e867623dc34b593"
    "fbe8580a1df21a001500e2"
) + bytes(226)


def decode(data: bytes, direction: Direction = Direction.C2S) -> list[Frame | Noise]:
    dec = MbapDecoder(STREAM, direction)
    return dec.feed(data, 1.0) + dec.flush(2.0)


def frames(items: list[Frame | Noise]) -> list[Frame]:
    return [x for x in items if isinstance(x, Frame)]


def test_http_request_to_502_is_all_noise() -> None:
    out = decode(HTTP)
    assert frames(out) == []
    assert len(out) == 1 and out[0].raw == HTTP
    assert out[0].ts == 1.0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(1, len(HTTP) - 1), max_size=6))
def test_http_request_any_chunking_is_all_noise(cuts: list[int]) -> None:
    dec = MbapDecoder(STREAM, Direction.C2S)
    out: list[Frame | Noise] = []
    prev = 0
    for cut in [*sorted(set(cuts)), len(HTTP)]:
        out += dec.feed(HTTP[prev:cut], 1.0)  # a cut right after "43" must not corroborate
        prev = cut
    out += dec.flush(2.0)
    assert frames(out) == []
    assert b"".join(x.raw for x in out) == HTTP


def test_tls_client_hello_to_502_is_all_noise() -> None:
    out = decode(CLIENT_HELLO)
    assert frames(out) == []
    assert b"".join(x.raw for x in out) == CLIENT_HELLO


def test_fresh_tls_client_hellos_make_no_frames() -> None:
    for _ in range(20):  # random, key share and padding vary per hello
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        ctx.check_hostname = False
        ctx.verify_mode = ssl.CERT_NONE
        incoming, outgoing = ssl.MemoryBIO(), ssl.MemoryBIO()
        tls = ctx.wrap_bio(incoming, outgoing, server_hostname="plc.example")
        try:
            tls.do_handshake()
        except ssl.SSLWantReadError:
            pass
        hello = outgoing.read()
        assert hello[:1] == b"\x16"
        assert frames(decode(hello)) == []


USER = bytes.fromhex("00 09 00 00 00 04 07 41 42 43")  # user-defined fc 0x41


def test_unknown_code_after_noise_corroborated_by_next_header() -> None:
    garbage = b"\xde\xad\xbe\xef"
    out = decode(garbage + USER + REQ_03)
    assert [type(x) for x in out] == [Noise, Frame, Frame]
    assert [f.raw for f in frames(out)] == [USER, REQ_03]


def test_unknown_code_after_noise_corroborated_by_end_of_stream() -> None:
    out = decode(b"\xde\xad\xbe\xef" + USER)
    assert [type(x) for x in out] == [Noise, Frame]
    assert out[1].raw == USER
    assert out[1].ts == 1.0  # when its last byte arrived, not the flush time


def test_unknown_code_followed_by_non_header_is_noise() -> None:
    data = b"\xde\xad\xbe\xef" + USER + b"\r\n\r\n\r\n\r\n"
    out = decode(data)
    assert frames(out) == [] and b"".join(x.raw for x in out) == data


def test_known_code_consistent_length_still_resyncs_at_once() -> None:
    dec = MbapDecoder(STREAM, Direction.C2S)
    out = dec.feed(b"\xde\xad\xbe\xef" + REQ_03, 1.0)
    assert [type(x) for x in out] == [Noise, Frame]


def test_mbap_length_255_is_decoded_and_malformed() -> None:
    # Schneider UMAS (fc 0x5A): MBAP length 255, one over the spec's 254.
    pdu = bytes([0x5A, 0x00, 0x02]) + bytes(range(251))
    adu = encode_adu(0x1234, 0xFF, pdu)
    assert adu[4:6] == b"\x00\xff"
    for direction in (Direction.C2S, Direction.S2C):
        out = decode(REQ_03 + adu + REQ_03, direction)
        assert [type(x) for x in out] == [Frame, Frame, Frame]
        f = out[1]
        assert isinstance(f, Frame)
        assert (f.raw, f.tid, f.unit, f.pdu.fc) == (adu, 0x1234, 0xFF, 0x5A)
        assert f.pdu.malformed == "MBAP length 255 exceeds 254"
    # a malformed read response keeps its own reasons after the length note
    resp = encode_adu(1, 1, bytes([0x03, 0xFD]) + bytes(252))
    [f] = frames(decode(resp, Direction.S2C))
    assert f.pdu.kind is Kind.RESPONSE
    assert f.pdu.malformed is not None
    assert f.pdu.malformed.startswith("MBAP length 255 exceeds 254; ")


def test_mbap_length_256_is_noise() -> None:
    adu = encode_adu(1, 1, bytes([0x5A]) + bytes(254))
    out = decode(adu + REQ_03)
    assert out[0].reason == "bad MBAP length 256"  # type: ignore[union-attr]
    assert frames(out)[-1].raw == REQ_03


def test_length_255_after_noise_is_a_resync_point() -> None:
    adu = encode_adu(7, 1, bytes([0x5A, 0x00]) + bytes(252))
    out = decode(b"\xde\xad\xbe\xef" + adu + REQ_03)
    assert [type(x) for x in out] == [Noise, Frame, Frame]


def test_short_garbage_reply_is_one_noise_record_stamped_on_arrival() -> None:
    # was a noise record + "truncated ADU at end of stream" at the end
    dec = MbapDecoder(STREAM, Direction.S2C)
    garbage = bytes.fromhex("DE AD BE EF 12 34 56")
    assert dec.feed(garbage, 3.0) == []
    out = dec.flush(60.0)
    assert len(out) == 1
    assert (out[0].raw, out[0].ts) == (garbage, 3.0)
    assert out[0].reason == "bad MBAP header (protocol id 0xBEEF)"


def test_noise_over_several_chunks_then_end_is_one_record() -> None:
    dec = MbapDecoder(STREAM, Direction.S2C)
    out = dec.feed(b"\x01\x02\x03\x04\x05", 1.0) + dec.feed(b"\x06\x07", 2.0)
    out += dec.feed(b"\x08", 3.0) + dec.flush(9.0)
    assert [(x.raw, x.ts) for x in out] == [(bytes(range(1, 9)), 1.0)]


def test_tick_reports_noise_run_after_silence() -> None:
    dec = MbapDecoder(STREAM, Direction.S2C, silence=0.5)
    assert dec.next_deadline() is None
    assert dec.feed(b"\xde\xad\xbe\xef\x01\x02\x03\x04\x05", 1.0) == []
    assert dec.next_deadline() == 1.5
    assert dec.tick(1.4) == []
    out = dec.tick(1.5)
    assert sum(len(x.raw) for x in out) >= 6 and out[0].ts == 1.0
    assert dec.next_deadline() is None  # nothing more until new bytes


def test_tick_takes_resync_candidate_ending_the_bytes() -> None:
    # a user-defined request after noise: the client then waits for the answer,
    # so no next header comes; the silence corroborates it
    dec = MbapDecoder(STREAM, Direction.C2S, silence=0.5)
    assert dec.feed(b"\xde\xad\xbe\xef" + USER, 1.0) == []
    out = dec.tick(2.0)
    assert [type(x) for x in out] == [Noise, Frame]
    assert out[1].raw == USER and out[1].ts == 1.0
    assert dec.next_deadline() is None


def test_tick_leaves_partial_adu_in_sync_alone() -> None:
    dec = MbapDecoder(STREAM, Direction.C2S, silence=0.5)
    assert dec.feed(REQ_03[:5], 1.0) == []
    assert dec.next_deadline() is None
    assert dec.tick(100.0) == []
    assert [f.raw for f in frames(dec.feed(REQ_03[5:], 101.0))] == [REQ_03]


def test_a_candidate_corroborated_later_keeps_the_time_its_bytes_arrived() -> None:
    """Noise, then a header whose code has no predictable length (0x22) at t=1; the next
    header that corroborates it arrives at t=2: the frame is stamped 1, not 2 (zeek
    fuzz-72 frame 7)."""
    dec = MbapDecoder(STREAM, Direction.C2S)
    first = dec.feed(
        bytes.fromhex("00 00") + bytes.fromhex("00 02 00 00 00 06 01 22 00 00 00 00"), 1.0
    )
    assert not [x for x in first if isinstance(x, Frame)]  # undecided yet
    later = dec.feed(REQ_03, 2.0)
    frames = [x for x in later if isinstance(x, Frame)]
    assert [(f.pdu.fc, f.ts) for f in frames] == [(0x22, 1.0), (0x03, 2.0)]
