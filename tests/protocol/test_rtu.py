"""RTU stream decoder: byte tables, a timing-free bus, noise, CRC errors, the real Solis log."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from mbmon.model import Direction, Frame, Kind, Noise, Stream, Transport
from mbmon.protocol.rtu import RtuDecoder, encode_rtu, t35

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "captures" / "real"
SOLIS = REAL / "rtu_log__candlerb__solis_packet_log.md"

BUS = Stream(0, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0")
OVER_TCP = Stream(1, Transport.RTU_OVER_TCP, "10.0.0.2:40000", "10.0.0.1:502")


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# Request/response pairs from the Modbus spec examples (unit 0x11), CRC appended.
PAIRS: dict[str, tuple[bytes, bytes]] = {
    "01": (h("11 01 00 13 00 25 0E 84"), h("11 01 05 CD 6B B2 0E 1B 45 E6")),
    "02": (h("11 02 00 C4 00 16 BA A9"), h("11 02 03 AC DB 35 20 18")),
    "03": (h("11 03 00 6B 00 03 76 87"), h("11 03 06 AE 41 56 52 43 40 49 AD")),
    "04": (h("11 04 00 08 00 01 B2 98"), h("11 04 02 00 0A F8 F4")),
    "05": (h("11 05 00 AC FF 00 4E 8B"), h("11 05 00 AC FF 00 4E 8B")),
    "06": (h("11 06 00 01 00 03 9A 9B"), h("11 06 00 01 00 03 9A 9B")),
    "0F": (h("11 0F 00 13 00 0A 02 CD 01 BF 0B"), h("11 0F 00 13 00 0A 26 99")),
    "10": (h("11 10 00 01 00 02 04 00 0A 01 02 C6 F0"), h("11 10 00 01 00 02 12 98")),
    "exception": (h("0A 01 04 A1 00 01 AC 63"), h("0A 81 02 B0 53")),
}

ALL = b"".join(req + resp for req, resp in PAIRS.values())
ALL_RAW = [adu for pair in PAIRS.values() for adu in pair]
ALL_DIRS = [Direction.C2S, Direction.S2C] * len(PAIRS)


def decode(data: bytes, direction: Direction = Direction.BUS) -> list[Frame | Noise]:
    dec = RtuDecoder(BUS if direction is Direction.BUS else OVER_TCP, direction)
    return dec.feed(data, 1.0) + dec.flush(2.0)


def frames(items: list[Frame | Noise]) -> list[Frame]:
    return [x for x in items if isinstance(x, Frame)]


def noises(items: list[Frame | Noise]) -> list[Noise]:
    return [x for x in items if isinstance(x, Noise)]


def key(f: Frame) -> tuple[object, ...]:
    return (f.unit, f.tid, f.direction, f.raw, f.pdu)


@pytest.mark.parametrize("name", list(PAIRS))
def test_pair_on_bus(name: str) -> None:
    req, resp = PAIRS[name]
    out = decode(req + resp)
    assert noises(out) == []
    fq, fr = frames(out)
    assert (fq.raw, fq.direction, fq.tid, fq.crc_ok, fq.ts) == (req, Direction.C2S, None, True, 1.0)
    assert (fr.raw, fr.direction, fr.tid, fr.crc_ok) == (resp, Direction.S2C, None, True)
    assert fq.unit == fr.unit == req[0]
    assert fq.pdu.raw == req[1:-2]
    assert fr.pdu.raw == resp[1:-2]
    assert fq.pdu.kind is Kind.REQUEST
    assert fq.pdu.fc == fr.pdu.fc == req[1]
    assert fr.pdu.kind is (Kind.EXCEPTION if name == "exception" else Kind.RESPONSE)
    # one byte per chunk gives the same frames
    dec = RtuDecoder(BUS)
    parts: list[Frame | Noise] = []
    for b in req + resp:
        parts += dec.feed(bytes([b]), 1.0)
    parts += dec.flush(2.0)
    assert [key(f) for f in frames(parts)] == [key(fq), key(fr)]


def test_decoded_fields() -> None:
    out = frames(decode(ALL))
    by_raw = {f.raw: f for f in out}
    r03 = by_raw[PAIRS["03"][1]]
    assert r03.pdu.values == (0xAE41, 0x5652, 0x4340)
    q10 = by_raw[PAIRS["10"][0]]
    assert (q10.pdu.address, q10.pdu.count, q10.pdu.values) == (1, 2, (0x000A, 0x0102))
    exc = by_raw[PAIRS["exception"][1]]
    assert (exc.unit, exc.pdu.fc, exc.pdu.exception_code) == (0x0A, 0x01, 2)


def test_bus_stream_both_directions_no_timing() -> None:
    out = decode(ALL)
    assert noises(out) == []
    assert [f.raw for f in frames(out)] == ALL_RAW
    assert [f.direction for f in frames(out)] == ALL_DIRS


def test_bus_stream_split_at_every_offset() -> None:
    whole = [key(f) for f in frames(decode(ALL))]
    for cut in range(0, len(ALL) + 1, 3):
        for cut2 in (cut + 1, cut + 7):
            dec = RtuDecoder(BUS)
            out = (
                dec.feed(ALL[:cut], 1.0)
                + dec.feed(ALL[cut:cut2], 2.0)
                + dec.feed(ALL[cut2:], 3.0)
                + dec.flush(4.0)
            )
            assert noises(out) == [], (cut, cut2)
            assert [key(f) for f in frames(out)] == whole, (cut, cut2)


def test_write_echo_is_response_only_when_its_request_is_pending() -> None:
    # 05/06 responses echo the request byte for byte: only the pending request
    # tells them apart. A repeat with nothing pending is another request.
    req = PAIRS["06"][0]
    out = frames(decode(req + req + req))
    assert [f.direction for f in out] == [Direction.C2S, Direction.S2C, Direction.C2S]


def test_echo_shaped_frame_from_another_unit_is_a_request() -> None:
    # Unit 0x11 does not answer its 06; the master then writes to unit 0x12.
    # Same function code, same length: only the unit says it is no response.
    first = PAIRS["06"][0]
    other = encode_rtu(0x12, h("06 00 01 00 03"))
    out = frames(decode(first + other + other))
    assert [(f.unit, f.direction) for f in out] == [
        (0x11, Direction.C2S),
        (0x12, Direction.C2S),
        (0x12, Direction.S2C),
    ]


def test_broadcast_expects_no_response() -> None:
    bcast = encode_rtu(0, h("06 00 01 00 03"))
    out = frames(decode(bcast + bcast + PAIRS["06"][0] + PAIRS["06"][1]))
    assert [f.direction for f in out] == [
        Direction.C2S,  # broadcast
        Direction.C2S,  # the same bytes again: a repeat, not an echo
        Direction.C2S,
        Direction.S2C,
    ]
    assert [f.unit for f in out] == [0, 0, 0x11, 0x11]


def test_noise_bytes_between_frames() -> None:
    req, resp = PAIRS["03"]
    junk = h("00 FF")
    out = decode(req + junk + resp + junk + PAIRS["04"][0])
    assert [type(x) for x in out] == [Frame, Noise, Frame, Noise, Frame]
    n = out[1]
    assert isinstance(n, Noise)
    assert (n.raw, n.direction, n.stream) == (junk, Direction.BUS, BUS)
    assert n.reason == "no valid frame (bad CRC)"
    assert [f.direction for f in frames(out)] == [Direction.C2S, Direction.S2C, Direction.C2S]


def test_corrupted_crc_becomes_noise_and_decoder_recovers() -> None:
    req, resp = PAIRS["03"]
    bad = resp[:-1] + bytes([resp[-1] ^ 0x01])
    nxt_req, nxt_resp = PAIRS["04"]
    dec = RtuDecoder(BUS)
    out = dec.feed(req + bad + nxt_req + nxt_resp, 1.0) + dec.flush(2.0)
    assert [f.raw for f in frames(out)] == [req, nxt_req, nxt_resp]
    assert [f.direction for f in frames(out)] == [Direction.C2S, Direction.C2S, Direction.S2C]
    [n] = noises(out)
    assert n.raw == bad
    assert n.reason == "no valid frame (bad CRC)"
    assert dec.stats == {"frames": 3, "noise_bytes": len(bad), "crc_errors": 1, "timing_gaps": 0}


def test_corrupted_payload_byte() -> None:
    req = PAIRS["10"][0]
    bad = req[:7] + bytes([req[7] ^ 0x40]) + req[8:]
    out = decode(bad + PAIRS["01"][0] + PAIRS["01"][1])
    assert sum(len(n.raw) for n in noises(out)) == len(bad)
    assert [f.raw for f in frames(out)] == list(PAIRS["01"])


def test_unknown_function_code_found_by_crc_scan() -> None:
    # User-defined function code 0x41: no predictable length, CRC scan finds both.
    req = encode_rtu(0x11, h("41 01 02 03"))
    resp = encode_rtu(0x11, h("41 AA BB CC DD EE"))
    out = decode(req + resp + PAIRS["03"][0])
    assert noises(out) == []
    assert [f.raw for f in frames(out)] == [req, resp, PAIRS["03"][0]]
    assert [f.direction for f in frames(out)] == [Direction.C2S, Direction.S2C, Direction.C2S]
    assert frames(out)[0].pdu.fields["data"] == h("01 02 03")


def test_read_device_identification_response_found_by_crc_scan() -> None:
    req = encode_rtu(0x11, h("2B 0E 01 00"))
    resp = encode_rtu(
        0x11, h("2B 0E 01 01 00 00 02") + h("00 05") + b"HIWIN" + h("01 04") + b"RA60"
    )
    out = decode(req + resp)
    assert noises(out) == []
    fq, fr = frames(out)
    assert (fq.raw, fq.direction) == (req, Direction.C2S)
    assert (fr.raw, fr.direction) == (resp, Direction.S2C)
    assert fr.pdu.fields["objects"] == ((0, "HIWIN"), (1, "RA60"))


def test_unknown_code_waits_for_enough_bytes_then_flush_settles() -> None:
    dec = RtuDecoder(BUS)
    # 0x41 with no valid CRC in sight: the decoder cannot tell yet and waits
    assert dec.feed(h("11 41 01 02 03"), 1.0) == []
    out = dec.flush(2.0)
    assert [type(x) for x in out] == [Noise]
    assert out[0].raw == h("11 41 01 02 03")
    assert out[0].reason == "no valid frame (unknown function code 0x41)"


def test_flush_reports_truncated_tail() -> None:
    req, resp = PAIRS["03"]
    dec = RtuDecoder(BUS)
    out = dec.feed(req + resp[:5], 1.0)
    assert [f.raw for f in frames(out)] == [req]
    tail = dec.flush(3.0)
    assert sum(len(n.raw) for n in noises(tail)) == 5
    assert noises(tail)[0].reason == "truncated frame at end of stream"
    assert frames(tail) == []
    assert dec.flush(4.0) == []


def test_reset_discards_buffer_and_pending_request() -> None:
    req, resp = PAIRS["06"]
    dec = RtuDecoder(BUS)
    assert frames(dec.feed(req + resp[:3], 1.0))[0].direction is Direction.C2S
    [n] = dec.reset(2.0)
    assert (n.raw, n.reason, n.ts) == (resp[:3], "discarded after gap", 1.0)  # when it arrived
    # the request is forgotten: the echo bytes are now a request
    [f] = dec.feed(resp, 3.0)
    assert isinstance(f, Frame)
    assert f.direction is Direction.C2S


def test_known_direction_rtu_over_tcp() -> None:
    req, resp = PAIRS["05"]
    [f] = frames(decode(resp, Direction.S2C))
    assert f.direction is Direction.S2C
    assert f.pdu.kind is Kind.RESPONSE
    [g] = frames(decode(req, Direction.C2S))
    assert g.direction is Direction.C2S
    # an exception function code cannot be a request
    out = decode(PAIRS["exception"][1], Direction.C2S)
    assert frames(out) == []
    assert noises(out)[0].raw == PAIRS["exception"][1]
    [e] = frames(decode(PAIRS["exception"][1], Direction.S2C))
    assert e.pdu.kind is Kind.EXCEPTION


def test_every_byte_is_accounted_for() -> None:
    data = h("FF 00 13") + ALL[:40] + h("AA") + ALL[40:] + h("11 03 00")
    dec = RtuDecoder(BUS)
    out: list[Frame | Noise] = []
    for i in range(0, len(data), 5):
        out += dec.feed(data[i : i + 5], float(i))
    out += dec.flush(999.0)
    assert sum(len(x.raw) for x in out) == len(data)
    assert dec.stats["noise_bytes"] == sum(len(n.raw) for n in noises(out))
    assert dec.stats["frames"] == len(frames(out))


# ---------------------------------------------------------------- timing hints


def test_t35() -> None:
    assert t35(9600) == pytest.approx(3.5 * 11 / 9600)
    assert t35(19200) == pytest.approx(3.5 * 11 / 19200)
    assert t35(115200) == 0.00175


def test_silence_settles_leftover_noise() -> None:
    # Unknown code 0x41 and no CRC in sight: without timing only 256 bytes (or
    # the end of the stream) settle it, so the request after it waits too.
    junk = h("11 41 41 41 41")
    req = PAIRS["03"][0]
    plain = RtuDecoder(BUS)
    assert plain.feed(junk, 1.0) == []
    assert plain.feed(req, 2.0) == []
    assert [type(x) for x in plain.flush(3.0)] == [Noise, Frame]
    # With the baud rate, a second of silence ends the junk: the request is
    # decoded at once. The junk could still be the start of a frame of
    # unpredictable length delivered late (USB adapters bunch bytes), so it
    # becomes noise only with the next bytes, when a frame of its own starts
    # right after the silence.
    timed = RtuDecoder(BUS, baudrate=9600)
    assert timed.feed(junk, 1.0) == []
    out = timed.feed(req, 2.0)
    assert [type(x) for x in out] == [Noise, Frame]
    assert out[0].raw == junk
    assert out[0].ts == 1.0
    assert out[1].raw == req
    assert timed.stats["timing_gaps"] == 1


def test_silence_settles_junk_before_a_frame_it_cannot_swallow() -> None:
    # junk of unknown code, then a whole request, then a silence: the request
    # frames on its own before the silence, so the junk is noise at once
    junk = h("11 41 41")
    req = PAIRS["03"][0]
    timed = RtuDecoder(BUS, baudrate=9600)
    assert timed.feed(junk + req, 1.0) == []  # no timing decision yet
    out = timed.tick(1.5)
    assert [(type(x), x.raw) for x in out] == [(Noise, junk), (Frame, req)]


def test_silence_never_splits_a_frame_whose_length_is_known() -> None:
    # USB adapters bunch bytes: a late chunk looks like silence but the frame
    # continues. A predicted frame that is not complete keeps waiting.
    req, resp = PAIRS["03"]
    dec = RtuDecoder(BUS, baudrate=9600)
    out = dec.feed(req + resp[:4], 1.0)
    out += dec.feed(resp[4:], 1.5)
    assert [f.raw for f in frames(out)] == [req, resp]
    assert noises(out) == []
    assert dec.stats["timing_gaps"] == 1


def test_back_to_back_chunks_are_no_silence() -> None:
    req, resp = PAIRS["03"]
    dec = RtuDecoder(BUS, baudrate=9600)
    char = 11 / 9600
    dec.feed(req, 1.0)
    dec.feed(resp, 1.0 + len(resp) * char + 0.001)  # 1 ms gap < t3.5 (4 ms)
    assert dec.stats["timing_gaps"] == 0


# ---------------------------------------------------------------- real log


def _solis_frames() -> list[tuple[Direction, bytes]]:
    if not SOLIS.exists():
        pytest.skip(f"{SOLIS.name} absent: ../shared/captures/real absent")
    out = []
    for line in SOLIS.read_text().splitlines():
        # "->0104...": request, "-<0104...": response; lines with "...." or "x"
        # redactions fail the pattern and are skipped.
        m = re.fullmatch(r"\s*(?::[0-9.]+\s*)?-([<>])([0-9A-Fa-f]+)\s*", line)
        if m:
            direction = Direction.C2S if m.group(1) == ">" else Direction.S2C
            out.append((direction, bytes.fromhex(m.group(2))))
    return out


def test_solis_log_bus_stream() -> None:
    expected = _solis_frames()
    assert len(expected) == 42  # the complete frames of the log
    bus = b"".join(raw for _, raw in expected)
    dec = RtuDecoder(BUS)
    out = dec.feed(bus, 1.0) + dec.flush(2.0)
    assert noises(out) == []
    assert [(f.direction, f.raw) for f in frames(out)] == expected
    fc = {f.raw: f for f in frames(out)}
    assert fc[h("01 84 02 C2 C1")].pdu.exception_code == 2
    assert fc[h("01 04 02 31 05 6C A3")].pdu.values == (0x3105,)
    # chunked in odd sizes it decodes the same
    dec = RtuDecoder(BUS)
    parts: list[Frame | Noise] = []
    for i in range(0, len(bus), 13):
        parts += dec.feed(bus[i : i + 13], float(i))
    parts += dec.flush(9e9)
    assert [(f.direction, f.raw) for f in frames(parts)] == expected
