"""Throughput of the RTU bus decoder on a 10 MB timing-free bus dump with noise.

    python bench/rtu_throughput.py                 # 10 MB, 4 KiB reads, decoder and pipeline
    python bench/rtu_throughput.py --mb 2 --read 64
    python bench/rtu_throughput.py --mb 2 --limit 400000 --decoder-only   # under callgrind

Instructions per byte (callgrind, start-up and table builds cancel out): run
the decoder alone on the first 100 KB and on the first 400 KB of the 2 MB dump
and divide the difference by 300,000 (``docs/performance.md``).

What this script owns: the synthetic dump (built once per size and seed, cached
in ``bench/out/``) and the figures. The dump is what an RS485 tap sees on a busy
bus: request/response pairs of function codes 01 02 03 04 05 06 0F 10 17 to
units 1-8 (register values random), about 2 % exception answers, and between
about 1 % of the exchanges a run of 1-6 noise bytes (line glitches) or a frame
with a broken CRC. No timing (no baud rate): framing is length prediction +
CRC only. It is fed in ``--read``-byte chunks as a serial reader would deliver
it to (a) :class:`mbmon.protocol.rtu.RtuDecoder` alone and (b) the whole
:class:`mbmon.pipeline.Pipeline` (decoder, pairing, records), and the script
reports MB/s, frames/s, the frame and noise counts (checked against what was
written) and the target (decoder >= 1 MB/s, ~100x a 115200-baud line).
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mbmon.model import Chunk, Direction, Stream, Transport
from mbmon.pipeline import Pipeline
from mbmon.protocol.rtu import RtuDecoder, encode_rtu

OUT = Path(__file__).resolve().parent / "out"
TARGET = 1.0  # MB/s
LINE = 115200 / 11 / 1e6  # MB/s of a saturated 115200-baud line


def _exchange(rng: random.Random) -> tuple[bytes, bytes]:
    unit = rng.randint(1, 8)
    fc = rng.choice((1, 2, 3, 4, 5, 6, 15, 16, 23, 3, 3, 4))
    addr = rng.randrange(0, 4000)
    if fc in (1, 2):
        n = rng.randint(1, 64)
        req = bytes([fc]) + addr.to_bytes(2) + n.to_bytes(2)
        nb = (n + 7) // 8
        resp = bytes([fc, nb]) + rng.randbytes(nb)
    elif fc in (3, 4):
        n = rng.randint(1, 32)
        req = bytes([fc]) + addr.to_bytes(2) + n.to_bytes(2)
        resp = bytes([fc, 2 * n]) + rng.randbytes(2 * n)
    elif fc == 5:
        req = bytes([5]) + addr.to_bytes(2) + rng.choice((b"\xff\x00", b"\x00\x00"))
        resp = req
    elif fc == 6:
        req = bytes([6]) + addr.to_bytes(2) + rng.randbytes(2)
        resp = req
    elif fc == 15:
        n = rng.randint(1, 40)
        nb = (n + 7) // 8
        req = bytes([15]) + addr.to_bytes(2) + n.to_bytes(2) + bytes([nb]) + rng.randbytes(nb)
        resp = req[:5]
    elif fc == 16:
        n = rng.randint(1, 20)
        req = bytes([16]) + addr.to_bytes(2) + n.to_bytes(2) + bytes([2 * n]) + rng.randbytes(2 * n)
        resp = req[:5]
    else:
        r, w = rng.randint(1, 10), rng.randint(1, 10)
        req = (
            bytes([23])
            + addr.to_bytes(2)
            + r.to_bytes(2)
            + addr.to_bytes(2)
            + w.to_bytes(2)
            + bytes([2 * w])
            + rng.randbytes(2 * w)
        )
        resp = bytes([23, 2 * r]) + rng.randbytes(2 * r)
    if rng.random() < 0.02:
        resp = bytes([fc | 0x80, rng.choice((1, 2, 3, 4))])
    return encode_rtu(unit, req), encode_rtu(unit, resp)


def build(size: int, seed: int) -> tuple[bytes, int, int]:
    """The dump, the number of valid frames and of noise bytes written."""
    rng = random.Random(seed)
    parts: list[bytes] = []
    total = frames = noise = 0
    while total < size:
        if rng.random() < 0.01:
            if rng.random() < 0.5:
                junk = bytes([0x00]) + rng.randbytes(rng.randint(0, 5))
            else:
                bad = bytearray(_exchange(rng)[0])
                bad[-1] ^= 0xA5
                junk = bytes(bad)
            parts.append(junk)
            noise += len(junk)
            total += len(junk)
        req, resp = _exchange(rng)
        parts.append(req + resp)
        frames += 2
        total += len(req) + len(resp)
    return b"".join(parts), frames, noise


def _found(got: int, written: int) -> str:
    """How the frames found compare with the valid frames written (noise can
    form a frame with a valid CRC by chance: a few more are no loss)."""
    if got == written:
        return "all found"
    if got > written:
        return f"{got - written} more than written: noise framed by a chance CRC match"
    return f"MISSING {written - got} FRAMES"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=float, default=10.0, help="dump size in MB (10)")
    ap.add_argument("--read", type=int, default=4096, help="bytes per read (4096)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--limit", type=int, help="feed only the first LIMIT bytes of the dump")
    ap.add_argument("--decoder-only", action="store_true", help="skip the pipeline run")
    args = ap.parse_args()
    size = int(args.mb * 1e6)
    OUT.mkdir(exist_ok=True)
    cache = OUT / f"rtu_bus_{size}_{args.seed}.bin"
    meta = cache.with_suffix(".txt")
    if cache.exists() and meta.exists():
        data = cache.read_bytes()
        frames_written, noise_written = map(int, meta.read_text().split())
    else:
        data, frames_written, noise_written = build(size, args.seed)
        cache.write_bytes(data)
        meta.write_text(f"{frames_written} {noise_written}")
    if args.limit is not None:
        data = data[: args.limit]
    n = len(data)
    step = args.read
    chunks = [data[i : i + step] for i in range(0, n, step)]
    stream = Stream(0, Transport.RTU, "bus", "bus")
    print(
        f"dump: {n / 1e6:.1f} MB, {frames_written} frames, {noise_written} noise bytes, "
        f"{len(chunks)} reads of {step} bytes"
    )

    decoder = RtuDecoder(stream, Direction.BUS)
    got_frames = got_noise = 0
    c0 = time.process_time()
    t0 = time.perf_counter()
    for chunk in chunks:
        for item in decoder.feed(chunk, 0.0):
            if hasattr(item, "pdu"):
                got_frames += 1
            else:
                got_noise += len(item.raw)
    for item in decoder.flush(0.0):
        if hasattr(item, "pdu"):
            got_frames += 1
        else:
            got_noise += len(item.raw)
    dt = time.perf_counter() - t0
    cpu = time.process_time() - c0
    rate = n / dt / 1e6
    print(
        f"RtuDecoder: {dt:.2f} s wall ({cpu:.2f} s CPU: {n / cpu / 1e6:.2f} MB/s), "
        f"{rate:.2f} MB/s, {got_frames / dt:,.0f} frames/s; "
        f"{got_frames} frames, {got_noise} noise bytes "
        f"({_found(got_frames, frames_written) if args.limit is None else 'part of the dump'}); "
        "wall "
        f"{rate / LINE:.0f}x a saturated 115200-baud line; target >= {TARGET} MB/s: "
        f"{'met' if rate >= TARGET else 'NOT met'}"
    )

    if args.decoder_only:
        return 0
    pipeline = Pipeline()
    records = 0
    c0 = time.process_time()
    t0 = time.perf_counter()
    for chunk in chunks:
        records += len(pipeline.feed(Chunk(0.0, stream, Direction.BUS, chunk)))
    records += len(pipeline.finish())
    dt = time.perf_counter() - t0
    cpu = time.process_time() - c0
    c = pipeline.counts
    print(
        f"Pipeline (decoder + pairing + records): {dt:.2f} s wall ({cpu:.2f} s CPU: "
        f"{n / cpu / 1e6:.2f} MB/s), {n / dt / 1e6:.2f} MB/s, "
        f"{c['frames'] / dt:,.0f} frames/s; {c['frames']} frames, {c['noise_bytes']} noise "
        f"bytes, {records} records"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
