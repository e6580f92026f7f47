"""RTU: a CRC scan never swallows frames that validate on their own; time reaches
the decoder through tick."""

from __future__ import annotations

import random

from mbmon.model import Direction, Frame, Noise, Stream, Transport
from mbmon.protocol.crc import CRC_TABLE
from mbmon.protocol.rtu import RtuDecoder, _scan, encode_rtu, t35

BUS = Stream(0, Transport.RTU, "bus.bin", "bus.bin")


def _crc(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc = (crc >> 8) ^ CRC_TABLE[(crc ^ b) & 0xFF]
    return crc


def swallowing_dump() -> tuple[bytes, list[bytes]]:
    """A noise byte (AA) and a user-defined function code (41) before 12 valid
    frames, the last of which carries, in its register data, the CRC of
    everything from AA on: a scan from AA finds a "frame" ending there."""
    for seed in range(100):
        rng = random.Random(seed)
        frames = []
        for _ in range(5):
            addr, n = rng.randrange(1000), rng.randrange(1, 6)
            frames.append(
                encode_rtu(1, bytes([3]) + addr.to_bytes(2, "big") + n.to_bytes(2, "big"))
            )
            data = bytes(rng.randrange(256) for _ in range(2 * n))
            frames.append(encode_rtu(1, bytes([3, 2 * n]) + data))
        frames.append(encode_rtu(1, bytes([3, 0, 0, 0, 4])))
        d01 = bytes([rng.randrange(256), rng.randrange(256)])
        covered = bytes([0xAA, 0x41]) + b"".join(frames) + bytes([1, 3, 8]) + d01
        c = _crc(covered)
        rest = bytes(rng.randrange(256) for _ in range(4))
        frames.append(encode_rtu(1, bytes([3, 8]) + d01 + bytes([c & 0xFF, c >> 8]) + rest))
        dump = bytes([0xAA, 0x41]) + b"".join(frames)
        if _scan(dump, 0, min(256, len(dump))) == len(covered) + 2:
            return dump, frames
    raise AssertionError("no seed gives the deliberate CRC match")


def test_scan_does_not_swallow_valid_frames() -> None:
    dump, expected = swallowing_dump()
    assert len(expected) == 12
    for chunks in ([dump], [dump[i : i + 1] for i in range(len(dump))]):
        dec = RtuDecoder(BUS)
        out: list[Frame | Noise] = []
        for c in chunks:
            out += dec.feed(c, 0.0)
        out += dec.flush(0.0)
        got = [x for x in out if isinstance(x, Frame)]
        assert [f.raw for f in got] == expected
        assert [f.direction for f in got] == [Direction.C2S, Direction.S2C] * 6
        noise = [x for x in out if isinstance(x, Noise)]
        assert [n.raw for n in noise] == [b"\xaa\x41"]


def test_user_defined_frame_still_found_by_scan() -> None:
    user = encode_rtu(7, bytes([0x41, 1, 2, 3, 4, 5]))
    req = encode_rtu(1, bytes([3, 0, 0, 0, 2]))
    dec = RtuDecoder(BUS)
    out = dec.feed(req + user + req, 0.0) + dec.flush(0.0)
    assert [x.raw for x in out] == [req, user, req]


def test_tick_settles_partial_frame_after_silence() -> None:
    req = encode_rtu(1, bytes([3, 0, 0, 0, 2]))
    dec = RtuDecoder(BUS, silence=1.0)
    assert dec.feed(req + req[:5], 10.0)[0].raw == req
    assert dec.next_deadline() == 11.0
    assert dec.tick(10.5) == []
    [n] = dec.tick(11.0)
    assert isinstance(n, Noise) and (n.raw, n.ts) == (req[:5], 10.0)
    assert dec.next_deadline() is None and dec.tick(20.0) == []


def test_tick_reports_noise_run_at_t35_with_baudrate() -> None:
    req = encode_rtu(1, bytes([3, 0, 0, 0, 2]))
    bad = req[:-1] + bytes([req[-1] ^ 0xFF])  # CRC error
    dec = RtuDecoder(BUS, baudrate=9600, silence=1.0)
    assert [x.raw for x in dec.feed(req + bad, 5.0)] == [req]
    deadline = dec.next_deadline()
    assert deadline is not None and 5.0 + t35(9600) < deadline < 5.01
    # a predicted length inside the bad frame still waits (USB adapters bunch
    # bytes), and the noise run stays open for it: one run, one record
    assert dec.tick(deadline) == []
    assert dec.next_deadline() == 6.0
    [noise] = dec.tick(6.0)  # the long silence settles the rest
    assert isinstance(noise, Noise)
    assert (noise.raw, noise.ts, noise.reason) == (bad, 5.0, "no valid frame (bad CRC)")
    assert dec.stats["crc_errors"] == 1
    assert dec.next_deadline() is None


def test_tick_settles_unpredictable_scan_without_more_bytes() -> None:
    # a user-defined frame whose CRC match is not the only possible one is held
    # until 256 bytes or a silence; tick brings the silence
    user = encode_rtu(7, bytes([0x41, 1, 2, 3]))
    dec = RtuDecoder(BUS, silence=0.5)
    out = dec.feed(user[:-1], 1.0)
    assert out == []
    out = dec.feed(user[-1:], 1.1)
    out += dec.tick(1.6)
    assert [x.raw for x in out if isinstance(x, Frame)] == [user]
