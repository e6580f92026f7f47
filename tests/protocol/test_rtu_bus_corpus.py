"""The RS485 corpus through the RTU bus decoder (DESIGN rule 3).

* A frame whose CRC validates at a boundary the bus marks (a silence, the next
  frame lining up, the end of the stream) is a frame, flagged malformed where
  its fields disagree: libmodbus's quantity-0 writes.
* Noise is one record per run and never holds back or re-times the frames
  after it: each frame carries the time its own last byte arrived and is given
  out by the read that completes it, or at the latest t3.5 later (the tick).
* libmodbus's whole RTU unit-test session, split at every byte, with noise
  bursts between frames, in a USB adapter's 16 ms bursts, and after a stretch of
  wrong-baud garbage: every frame exactly once, at its own time.
"""

from __future__ import annotations

import itertools
import random

import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st
from rtu_corpus import (
    BAD_CRC,
    BAD_REQUESTS,
    BAUD,
    CHAR,
    GOOD,
    Delivered,
    bursts,
    bus_directions,
    drive,
    prompt,
    session,
    wire,
)

from mbmon.model import Direction, Frame, Noise, Stream, Transport
from mbmon.protocol.rtu import RtuDecoder, t35

BUS = Stream(0, Transport.RTU, "/dev/ttyUSB0", "/dev/ttyUSB0")
T35 = t35(BAUD)
PROMPT_BYTES = int(T35 / CHAR)  # the most bytes a prompt read holds: they span < t3.5


def frames(items: list) -> list[tuple[Direction, bytes]]:
    return [(x.direction, x.raw) for x in items if isinstance(x, Frame)]


def noises(items: list) -> list[Noise]:
    return [x for x in items if isinstance(x, Noise)]


def untimed(data: bytes, cuts: list[int] = ()) -> list[Frame | Noise]:
    dec = RtuDecoder(BUS)
    out: list[Frame | Noise] = []
    points = [0, *sorted(set(cuts)), len(data)]
    for a, b in itertools.pairwise(points):
        out += dec.feed(data[a:b], 0.0)
    return out + dec.flush(0.0)


# ---------------------------------------------------------------- bad requests


@pytest.mark.parametrize("req,answer", BAD_REQUESTS, ids=lambda b: b.hex()[:6])
def test_libmodbus_bad_request_is_a_malformed_frame(req: bytes, answer: bytes) -> None:
    assert any(raw == req for _, raw in session())
    data = req + answer
    for cut in range(len(data) + 1):  # split at every byte
        out = untimed(data, [cut])
        assert frames(out) == [(Direction.C2S, req), (Direction.S2C, answer)], cut
        assert noises(out) == []
    first = next(x for x in untimed(data) if isinstance(x, Frame))
    assert first.pdu.fc == req[1] and first.pdu.malformed
    if req[1] in (0x0F, 0x10) and req[6] == 0:  # byte count 0 and six data bytes: said so
        assert first.pdu.malformed and "byte count 0 but 6 data bytes" in first.pdu.malformed


@pytest.mark.parametrize("req,answer", BAD_REQUESTS[:2], ids=["10", "0F"])
def test_bad_request_on_a_timed_bus_is_framed_at_the_silence(req: bytes, answer: bytes) -> None:
    # the master's request, t3.5 of silence, the slave's answer 5 ms later
    dec = RtuDecoder(BUS, baudrate=BAUD, silence=1.0)
    assert dec.feed(req, 10.0) == []  # its fields predict 9 bytes: no boundary yet
    deadline = dec.next_deadline()
    assert deadline is not None and deadline <= 10.0 + T35 + 1e-5
    [f] = dec.tick(deadline)  # the silence marks its end: a frame, stamped when it arrived
    assert isinstance(f, Frame)
    assert (f.raw, f.direction, f.ts) == (req, Direction.C2S, 10.0)
    assert f.pdu.malformed
    [a] = dec.feed(answer, 10.005)
    assert isinstance(a, Frame)
    assert (a.raw, a.direction, a.ts) == (answer, Direction.S2C, 10.005)  # paired: an answer
    assert dec.stats["crc_errors"] == 0 and dec.stats["noise_bytes"] == 0


def test_bad_request_in_one_direction_rtu_over_tcp_or_the_proxy() -> None:
    # the proxy's master side decodes requests only (Direction.C2S)
    req = BAD_REQUESTS[0][0]
    dec = RtuDecoder(BUS, Direction.C2S, BAUD, silence=0.05)
    assert dec.feed(req[:4], 1.0) + dec.feed(req[4:], 1.0001) == []
    [f] = dec.tick(dec.next_deadline() or 0.0)
    assert isinstance(f, Frame) and f.raw == req and f.ts == 1.0001


# ---------------------------------------------------------------- noise and time


@pytest.mark.parametrize("baud", [BAUD, None])
def test_bad_crc_then_frames_each_on_time(baud: int | None) -> None:
    # the report: one bad-CRC read, then six good ones 0.3 s apart on a pty
    dec = RtuDecoder(BUS, baudrate=baud, silence=1.0)
    reads = [Delivered(0.0, BAD_CRC)] + [Delivered(0.3 * i, GOOD) for i in range(1, 7)]
    out = drive(dec, reads)
    got = [(at, x) for at, x in out if isinstance(x, Frame)]
    assert [x.ts for _, x in got] == [0.3 * i for i in range(1, 7)]  # its own time each
    for at, x in got:
        # shown by the read that completes it; without the baud rate (no silence
        # seen) the first waits at most for the next frame to line up with it
        assert at - x.ts <= (T35 + 1e-5 if baud else 0.3 + 1e-9)
    [noise] = noises([x for _, x in out])
    assert (noise.raw, noise.ts, noise.reason) == (BAD_CRC, 0.0, "no valid frame (bad CRC)")
    assert dec.stats["crc_errors"] == 1 and dec.stats["noise_bytes"] == 8


def test_noise_glued_to_a_frame_is_settled_at_the_silence() -> None:
    # one read: two noise bytes and a request; the answer comes after a silence
    req, resp = h("11 03 00 6B 00 03 76 87"), h("11 03 06 AE 41 56 52 43 40 49 AD")
    dec = RtuDecoder(BUS, baudrate=BAUD, silence=1.0)
    out = drive(dec, [Delivered(5.0, h("FF 03") + req), Delivered(5.01, resp)])
    assert frames([x for _, x in out]) == [(Direction.C2S, req), (Direction.S2C, resp)]
    at, f = next((at, x) for at, x in out if isinstance(x, Frame))
    assert f.ts == 5.0 and at <= 5.0 + T35 + 1e-5
    [n] = noises([x for _, x in out])
    assert n.raw == h("FF 03")


def test_late_reader_frame_between_noise_out_with_the_read_after_the_silence() -> None:
    # A reader hands over 19 bytes 1.8 ms (> t3.5) after the first came: the tick
    # t3.5 after the lone byte before them falls inside a frame, so the line looks
    # like a bursty adapter's and a frame between noise waits for one that lines it
    # up. Here the frame after the silence starts right at it: the read that brings
    # it decides the frame before, though a bad-CRC copy after that one needs more
    # bytes than are there to be told apart (it once waited for the next tick).
    request = h("11 01 01 30 00 01 FE A9")
    answer = h("11 01 01 01 94 88")
    noise = h("10 0F 01 30 00 25 05 CD 6B B2 0E 1B CC C1")
    frame = h("11 0F 01 30 00 25 05 CD 6B B2 0E 1B CC C1")
    bad = h("10 0F 01 30 00 25 97 73")
    last = h("11 0F 01 30 00 25 97 73")
    parts = [request, h("10 01 01 01 94 88"), answer, noise, frame, bad, last]
    bytes_at = wire(parts, [0.002, 0.0, 0.0, 0.002, 0.0, 0.0, 0.002])
    data = b"".join(parts)
    cut = [0, 1, 20, 56, len(data)]  # 1 byte, 19 late, the 36 before the silence, 8
    reads = [Delivered(bytes_at[b - 1][0], data[a:b]) for a, b in itertools.pairwise(cut)]
    dec = RtuDecoder(BUS, baudrate=BAUD, silence=1.0)
    out = drive(dec, reads)
    assert frames([x for _, x in out]) == [
        (Direction.C2S, request),
        (Direction.S2C, answer),
        (Direction.C2S, frame),
        (Direction.S2C, last),
    ]
    assert [x.raw for _, x in out if isinstance(x, Noise)] == [parts[1], noise, bad]
    [(at, f)] = [(at, x) for at, x in out if isinstance(x, Frame) and x.raw == frame]
    assert f.ts == reads[2].ts
    assert at == reads[3].ts  # with the next frame, not t3.5 after it


def test_scanned_frame_between_noise_out_with_the_frame_at_the_silence() -> None:
    # an unknown function code (0x42, length found by its CRC) with a noise byte
    # before and a bad-CRC copy of the answer after it, then a silence and the
    # answer. Inside the scanned frame "55 10 .." reads as a write request whose
    # byte count (at the answer) asks for 26 bytes; before the silence that is no
    # frame. The scanned frame starts right at the silence after the noise byte:
    # it is out t3.5 after its read at the latest (it once waited for the answer)
    frame, answer = h("11 42 00 00 00 00 7B 55"), h("11 C2 01 B1 65")
    dec = RtuDecoder(BUS, baudrate=BAUD, silence=1.0)
    reads = [
        Delivered(1.0, h("00")),
        Delivered(1.0 + 0.002 + 13 * CHAR, frame + h("10 C2 01 B1 65")),
        Delivered(1.0 + 0.004 + 18 * CHAR, answer),
    ]
    out = drive(dec, reads)
    assert frames([x for _, x in out]) == [(Direction.C2S, frame), (Direction.S2C, answer)]
    assert [x.raw for _, x in out if isinstance(x, Noise)] == [h("00"), h("10 C2 01 B1 65")]
    [(at, f)] = [(at, x) for at, x in out if isinstance(x, Frame) and x.raw == frame]
    assert f.ts == reads[1].ts
    assert at <= reads[1].ts + T35 + 1e-5  # not with the answer, which comes later
    assert reads[2].ts > reads[1].ts + T35 + 1e-5


def test_bad_request_cut_by_a_usb_burst_is_a_frame() -> None:
    # A USB adapter hands over the first 11 bytes of libmodbus's quantity-0 write
    # (its fields predict 9 bytes, its CRC is at 15), the rest 16 ms later with
    # the answer. The tick t3.5 after the first burst sees a silence: the bytes
    # fail their CRC at 9, yet nothing starts after them, so they may go on (it
    # once made them noise and lost the request)
    req, answer = BAD_REQUESTS[0]
    dec = RtuDecoder(BUS, baudrate=BAUD, silence=1.0)
    reads = [Delivered(1.016, req[:11]), Delivered(1.032, req[11:] + answer)]
    out = drive(dec, reads)
    assert frames([x for _, x in out]) == [(Direction.C2S, req), (Direction.S2C, answer)]
    assert noises([x for _, x in out]) == []
    assert [(at, x.ts) for at, x in out] == [(1.032, 1.032), (1.032, 1.032)]


def test_noise_at_a_silence_then_a_scanned_frame_each_on_time() -> None:
    # A bad-CRC copy of an unknown-function-code frame (0x42: its length is found
    # by its CRC), a silence, the frame with a bad-CRC answer glued to it, a
    # silence, the answer. The frame starts right at the silence: the bytes
    # before it are noise, and the frame is out within t3.5 (it once waited for
    # the answer's read, 4 ms past t3.5)
    noise, frame = h("12 42 00 00 00 00 7B 55"), h("11 42 00 00 00 00 7B 55")
    bad, answer = h("7A C2 01 B1 65"), h("11 C2 01 B1 65")
    reads = [
        Delivered(1.0, noise),
        Delivered(1.006, frame),
        Delivered(1.0065, bad),
        Delivered(1.012, answer),
    ]
    out = drive(RtuDecoder(BUS, baudrate=BAUD, silence=1.0), reads)
    assert frames([x for _, x in out]) == [(Direction.C2S, frame), (Direction.S2C, answer)]
    assert [x.raw for _, x in out if isinstance(x, Noise)] == [noise, bad]
    [(at, f)] = [(at, x) for at, x in out if isinstance(x, Frame) and x.raw == frame]
    # out with the next read (its last bytes could start a frame running past its
    # end until then), well within t3.5
    assert (f.ts, at) == (1.006, 1.0065)


def test_scanned_frame_glued_between_noise_out_at_the_silence() -> None:
    # The same bytes back to back, no silence between them until the answer's: on
    # a line whose silences have been real, the silence after them settles them.
    # The noise before reads as 0x42 too (no CRC match: noise); the frame lies
    # whole before the silence, found by its CRC, and is out t3.5 after its read
    # (it once waited for the answer's read)
    noise, frame = h("12 42 00 00 00 00 7B 55"), h("11 42 00 00 00 00 7B 55")
    bad, answer = h("7A C2 01 B1 65"), h("11 C2 01 B1 65")
    reads = [Delivered(1.0, noise + frame + bad), Delivered(1.006, answer)]
    out = drive(RtuDecoder(BUS, baudrate=BAUD, silence=1.0), reads)
    assert frames([x for _, x in out]) == [(Direction.C2S, frame), (Direction.S2C, answer)]
    assert [x.raw for _, x in out if isinstance(x, Noise)] == [noise, bad]
    [(at, f)] = [(at, x) for at, x in out if isinstance(x, Frame) and x.raw == frame]
    assert f.ts == 1.0 and at <= 1.0 + T35 + 1e-5


def test_usb_frame_between_noise_waits_at_most_the_timeout_past_its_arrival() -> None:
    # In bursts (a frame went on across a burst first: silences may be latency) a
    # frame with noise on both sides waits for frames to line up. Noise keeps
    # coming 16 ms later, ending in a bad request: the frame is out `silence` after
    # its own arrival, not `silence` after the last byte (it once was 16 ms late)
    frame = h("11 8F 03 05 F4")
    reads = [
        Delivered(0.5, GOOD[:4]),
        Delivered(0.516, GOOD[4:]),
        Delivered(1.0, h("00") + frame + h("10 10 01")),
        Delivered(1.016, h("60 00 00 00 02 2B 00 01 00 64 8C 88") + BAD_REQUESTS[0][0]),
    ]
    dec = RtuDecoder(BUS, baudrate=BAUD, silence=1.0)
    out = drive(dec, reads)
    assert dec._bounds.bursty
    assert frames([x for _, x in out]) == [
        (Direction.C2S, GOOD),
        (Direction.S2C, frame),
        (Direction.C2S, BAD_REQUESTS[0][0]),
    ]
    at = {x.raw: (t, x.ts) for t, x in out if isinstance(x, Frame)}
    assert at[frame] == (2.0, 1.0)  # `silence` after its own read, no later
    assert at[BAD_REQUESTS[0][0]] == (2.016, 1.016)
    assert sum(len(x.raw) for _, x in out) == sum(len(r.data) for r in reads)


def h(text: str) -> bytes:
    return bytes.fromhex(text)


# ---------------------------------------------------------------- the whole session

SESSION = session()
EXPECTED = bus_directions(SESSION)
SESSION_BYTES = b"".join(raw for _, raw in SESSION)


def test_session_untimed_whole_and_split_at_every_byte() -> None:
    assert frames(untimed(SESSION_BYTES)) == EXPECTED
    rng = random.Random(7)
    for cut in range(len(SESSION_BYTES) + 1):
        extra = rng.randrange(len(SESSION_BYTES) + 1)
        out = untimed(SESSION_BYTES, [cut, extra])
        assert frames(out) == EXPECTED, cut
        assert noises(out) == []


def _timeline(gaps: list[float]) -> list[Delivered]:
    return prompt([raw for _, raw in SESSION], gaps)


def _check_timed(out: list[tuple[float, Frame | Noise]], reads: list[Delivered], bound: float):
    got = [(at, x) for at, x in out if isinstance(x, Frame)]
    assert [(x.direction, x.raw) for _, x in got] == EXPECTED
    ends = []
    pos = 0
    arrivals = [r.ts for r in reads for _ in r.data]
    for _, x in got:
        pos = SESSION_BYTES.index(x.raw, pos) + len(x.raw)
        ends.append(arrivals[pos - 1])
    for (at, x), end in zip(got, ends, strict=True):
        assert x.ts == end  # the time its own last byte arrived
        assert at - end <= bound  # given out promptly


def test_session_on_a_prompt_bus_each_frame_at_its_own_time() -> None:
    rng = random.Random(3)
    gaps = [rng.choice([0.002, 0.005, 0.02, 0.3]) for _ in SESSION]
    reads = _timeline(gaps)
    out = drive(RtuDecoder(BUS, baudrate=BAUD, silence=1.0), reads)
    _check_timed(out, reads, T35 + 1e-5)


def test_session_in_usb_adapter_bursts() -> None:
    # the bytes go out back to back with 2-5 ms between frames; the adapter hands
    # them over every 16 ms, frames cut anywhere
    rng = random.Random(5)
    gaps = [rng.choice([0.002, 0.003, 0.005, 0.04]) for _ in SESSION]
    reads = bursts(wire([raw for _, raw in SESSION], gaps))
    assert len(reads) < len(SESSION)  # frames do share reads
    out = drive(RtuDecoder(BUS, baudrate=BAUD, silence=1.0), reads)
    _check_timed(out, reads, 0.016 + T35 + 1e-5)  # at the latest with the next burst
    assert noises([x for _, x in out]) == []


def test_wrong_baud_garbage_then_the_session() -> None:
    # what a reader at the wrong speed gets: framing errors read as 00 / FF and
    # shifted bits; then the line is right again
    rng = random.Random(9)
    garbage = bytes(rng.choice([0x00, 0xFF, 0xFE, 0x80, rng.randrange(256)]) for _ in range(400))
    dec = RtuDecoder(BUS, baudrate=BAUD, silence=1.0)
    reads = [Delivered(1.0 + i * 0.01, garbage[i : i + 40]) for i in range(0, 400, 40)]
    reads += [Delivered(r.ts + 10.0, r.data) for r in _timeline([0.005] * len(SESSION))]
    out = drive(dec, reads)
    items = [x for _, x in out]
    assert frames(items) == EXPECTED
    assert sum(len(n.raw) for n in noises(items)) == len(garbage)
    assert all(n.ts < 11.0 for n in noises(items))


# ---------------------------------------------------------------- noise bursts, any chunking

# Random draws: any regression of "each frame once, at its own time, out within
# t3.5 (or --timeout in USB bursts)" fails. Sweep further with --hypothesis-seed=N
# and a larger max_examples (thousands of examples per seed pass locally).
CORPUS_SETTINGS = settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
_START = [i for i, (who, _) in enumerate(SESSION) if who == ">"]


@st.composite
def noisy_bus(draw: st.DrawFn) -> tuple[list[bytes], list[int]]:
    """A stretch of the session with noise bursts (random bytes or a bad-CRC copy
    of a frame) before some frames; returns the parts and which parts are noise."""
    start = draw(st.sampled_from(_START))
    length = draw(st.integers(4, 14))
    parts: list[bytes] = []
    noisy: list[int] = []
    for _, raw in SESSION[start : start + length]:
        if draw(st.integers(0, 3)) == 0:
            if draw(st.booleans()):
                junk = draw(st.binary(min_size=1, max_size=12))
            else:
                bad = bytearray(raw)
                bad[draw(st.integers(0, len(bad) - 1))] ^= draw(st.integers(1, 255))
                junk = bytes(bad)
            noisy.append(len(parts))
            parts.append(junk)
        parts.append(raw)
    return parts, noisy


@CORPUS_SETTINGS
@given(
    noisy_bus(),
    st.lists(st.integers(0, 10_000), max_size=12),
    st.lists(st.sampled_from([0.0, 0.002, 0.005, 0.05, 0.3]), min_size=1, max_size=6),
    st.booleans(),
)
@example(
    bus=(
        [
            b"\x10\x05\x010\xff\x00\x8fY",
            b"\x11\x05\x010\xff\x00\x8fY",
            b"\x10\x05\x010\xff\x00\x8fY",
            b"\x11\x05\x010\xff\x00\x8fY",
            b"\x11\x01\x010\x00\x01\xfe\xa9",
            b"\x10\x01\x01\x01\x94\x88",
            b"\x11\x01\x01\x01\x94\x88",
            b"\x10\x0f\x010\x00%\x05\xcdk\xb2\x0e\x1b\xcc\xc1",
            b"\x11\x0f\x010\x00%\x05\xcdk\xb2\x0e\x1b\xcc\xc1",
            b"\x10\x0f\x010\x00%\x97s",
            b"\x11\x0f\x010\x00%\x97s",
            b"\x11\x01\x010\x00%\xfe\xb2",
            b"\x11\x01\x05\xcdk\xb2\x0e\x1bE\xe6",
            b"\x11\x02\x01\xc4\x00\x16\xbbU",
            b"\x11\x02\x03\xac\xdb5 \x18",
            b"\x11\x06\x01`\x124\x87\xcf",
        ],
        [0, 2, 5, 7, 9],
    ),
    cuts=[172],
    gaps=[0.0, 0.002, 0.0],
    usb=False,
).via("discovered failure")
def test_noise_bursts_any_chunking_each_frame_once_on_time(
    bus: tuple[list[bytes], list[int]], cuts: list[int], gaps: list[float], usb: bool
) -> None:
    parts, noisy = bus
    data = b"".join(parts)
    want = [raw for i, raw in enumerate(parts) if i not in noisy]
    whole = untimed(data)
    # a noise burst that frames by chance (or eats a frame's start into a valid
    # CRC) is no test of timing: the stream must decode right in one piece first
    assume([raw for _, raw in frames(whole)] == want)
    # the bytes on the wire: frames apart by at least t3.5 (the bus's rule), noise
    # back to back with its neighbours (gap 0) or apart too
    part_gaps = [gaps[i % len(gaps)] for i in range(len(parts))]
    for i in range(1, len(parts)):
        if i not in noisy and i - 1 not in noisy:
            part_gaps[i] = max(part_gaps[i], 0.002)
    bytes_at = wire(parts, part_gaps)
    if usb:  # the adapter hands over what came every 16 ms
        reads = bursts(bytes_at)
    else:  # a prompt reader: a read ends at every silence, and anywhere else
        points = {0, len(data), *(c % (len(data) + 1) for c in cuts)}
        edge = 0
        for part, gap in zip(parts, part_gaps, strict=True):
            if gap:
                points.add(edge)
            edge += len(part)
        # and hands over each byte within t3.5 of its arrival: a read holding more
        # bytes than t3.5 carries is late, the decoder's tick then falls inside a
        # frame and rightly takes the line for a bursty adapter's
        # (test_late_reader_frame_between_noise_out_with_the_read_after_the_silence)
        cut = sorted(points)
        for a, b in itertools.pairwise(cut):
            points.update(range(a + PROMPT_BYTES, b, PROMPT_BYTES))
        cut = sorted(points)
        reads = [Delivered(bytes_at[b - 1][0], data[a:b]) for a, b in itertools.pairwise(cut)]
    # the reads a silence follows (or the last): t3.5 later the decoder is ticked
    quiet = [
        r.ts
        for r, nxt in zip(reads, [*reads[1:], None], strict=True)
        if nxt is None or nxt.ts - len(nxt.data) * CHAR - r.ts > T35
    ]
    out = drive(RtuDecoder(BUS, baudrate=BAUD, silence=1.0), reads)
    items = [x for _, x in out]
    assert [raw for _, raw in frames(items)] == want  # each exactly once
    assert sum(len(x.raw) for x in items) == len(data)  # nothing lost, nothing twice
    arrivals = [r.ts for r in reads for _ in r.data]
    pos = 0
    for at, x in out:
        if isinstance(x, Frame):
            pos = data.index(x.raw, pos) + len(x.raw)
            assert x.ts == arrivals[pos - 1]  # the time its own last byte arrived
            # given out by the read that completes it, at the latest t3.5 into the
            # silence that follows it; in USB bursts a silence may be the adapter's
            # latency: a frame between noise waits for a frame that lines it up,
            # at most the settling silence (--timeout)
            silent = next(t for t in quiet if t >= x.ts)
            assert at <= (x.ts + 1.0 if usb else silent + T35 + 1e-5)
