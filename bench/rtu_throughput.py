"""Throughput of the RTU bus decoders on a 10 MB timing-free bus dump with noise.

    python bench/rtu_throughput.py                 # 10 MB, 4 KiB reads, decoders and pipeline
    python bench/rtu_throughput.py --mb 2 --read 64
    python bench/rtu_throughput.py --mb 2 --limit 400000 --decoder-only --which core   # callgrind

Instructions per byte (callgrind, start-up and table builds cancel out): run
one decoder alone (``--which pure`` or ``--which core``) on the first 100 KB and
on the first 400 KB of the 2 MB dump and divide the difference by 300,000
(``docs/performance.md``).

What this script owns: the synthetic dump (built once per size and seed, cached
in ``bench/out/``) and the figures. The dump is what an RS485 tap sees on a busy
bus: request/response pairs of function codes 01 02 03 04 05 06 0F 10 17 to
units 1-8 (register values random), about 2 % exception answers, and between
about 1 % of the exchanges a run of 1-6 noise bytes (line glitches) or a frame
with a broken CRC. No timing (no baud rate): framing is length prediction +
CRC only. It is fed in ``--read``-byte chunks as a serial reader would deliver
it, in the same run, to (a) the reference :class:`mbmon.protocol.rtu.RtuDecoder`,
(b) the compiled framer (``mbmon.core._rtu``) giving its packed output (frame
boundaries, no Python object per frame), (c) the compiled framer giving
Frame/Noise objects (what the pipeline asks of it), and (d) the whole
:class:`mbmon.pipeline.Pipeline` (decoder, pairing, records) with the reference
decoder and with the compiled framer. It reports CPU time (user + sys of this
process), MB/s and frames/s by CPU, the frame and noise counts (the same for
every decoder, checked against what was written) and the target (compiled
framer >= 20 MB/s of CPU).

``--read-cmd`` rows (``mbmon read --rtu-raw`` end to end, one child each, stdout to
/dev/null; CPU = user + sys of the child): text, ``--json`` and ``-q``, on the
compiled core and forced pure (``MBMON_NO_EXTENSIONS=1``), on the dump and on its
first fifth, so that start-up cancels out: MB/s of CPU whole and marginal
((size - size/5) / (CPU(size) - CPU(size/5))). ``--bus-cmd``: the same rows of
``mbmon read BUS.pcap``, the dump as a capture of an RTU bus (link type 147, a record
per read at a saturated 115200-baud line's times). ``--read-callgrind`` adds
callgrind instructions per byte, marginal the same way, on the first 100 KB and
400 KB of the dump (``--limit`` does not apply).

    python bench/rtu_throughput.py --mb 10 --decoder-only --read-cmd
    python bench/rtu_throughput.py --mb 10 --decoder-only --which core --bus-cmd
    python bench/rtu_throughput.py --mb 2 --decoder-only --which core --repeat 1 --read-callgrind
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mbmon import core
from mbmon.model import Chunk, Direction, Frame, Noise, Stream, Transport
from mbmon.protocol.rtu import RtuDecoder, encode_rtu

OUT = Path(__file__).resolve().parent / "out"
TARGET = 20.0  # MB/s of CPU, the compiled framer (issue's target for RTU decoding)
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


def _count(items: list[Frame | Noise]) -> tuple[int, int]:
    frames = noise = 0
    for item in items:
        if isinstance(item, Frame):
            frames += 1
        else:
            noise += len(item.raw)
    return frames, noise


def _objects(decoder: Any, chunks: list[bytes]) -> tuple[int, int]:
    """Feed the chunks to a decoder giving Frame and Noise objects: (frames, noise bytes)."""
    frames = noise = 0
    for chunk in chunks:
        f, n = _count(decoder.feed(chunk, 0.0))
        frames += f
        noise += n
    f, n = _count(decoder.flush(0.0))
    return frames + f, noise + n


def _packed(framer: Any, chunks: list[bytes]) -> tuple[int, int]:
    """Feed the chunks to the compiled framer's packed output (records dropped as they
    come, as a caller that only counts would): (frames, noise bytes)."""
    for chunk in chunks:
        framer.push(chunk, 0.0)
        framer.clear()
    framer.push_flush(0.0)
    framer.clear()
    return framer.stats["frames"], framer.stats["noise_bytes"]


def _timed(label: str, n: int, work: Any, repeat: int = 1) -> tuple[int, int, float]:
    """Run ``work`` ``repeat`` times; print and return its counts and CPU time per run
    (a run too short to time alone is repeated)."""
    c0 = time.process_time()
    for _ in range(repeat):
        frames, noise = work()
    cpu = (time.process_time() - c0) / repeat
    runs = f" (mean of {repeat} runs)" if repeat > 1 else ""
    print(
        f"{label}: {cpu:.3f} s CPU{runs}, {n / cpu / 1e6:.2f} MB/s (CPU), "
        f"{frames / cpu:,.0f} frames/s; {frames} frames, {noise} noise bytes"
    )
    return frames, noise, cpu


def _pipeline(chunks: list[bytes], stream: Stream, pure: bool) -> tuple[int, int]:
    """The whole pipeline (decoder, pairing, records): its RTU decoder the compiled
    framer (when built), or the reference decoder (``pure``)."""
    from mbmon import pipeline as pipes

    entry = pipes.decoder_entry(Transport.RTU)
    if pure:
        pipes.register_decoder(
            Transport.RTU, lambda s, d, c: RtuDecoder(s, d, c.baudrate, c.settle_after)
        )
    try:
        pipe = pipes.Pipeline()
        records = 0
        for chunk in chunks:
            records += len(pipe.feed(Chunk(0.0, stream, Direction.BUS, chunk)))
        records += len(pipe.finish())
    finally:
        pipes.register_decoder(Transport.RTU, entry.make, datagram=entry.datagram)
    return pipe.counts["frames"], pipe.counts["noise_bytes"]


READS = (("text", []), ("--json", ["--json"]), ("-q", ["-q"]))


def _part(data: bytes, cache: Path, size: int) -> Path:
    """The first ``size`` bytes of the dump as a file of its own (cached beside it)."""
    part = cache.with_name(f"{cache.stem}_first{size}.bin")
    if not part.exists() or part.stat().st_size != size:
        part.write_bytes(data[:size])
    return part


def _read_cmd(path: Path, extra: list[str], pure: bool, raw: bool = True) -> list[str]:
    """``mbmon read --rtu-raw PATH`` (``raw``), or ``mbmon read PATH`` of a bus capture."""
    from read_throughput import mbmon_cmd

    env = ["env", "MBMON_NO_EXTENSIONS=1"] if pure else []
    return [*env, *mbmon_cmd(), "read", *(["--rtu-raw"] if raw else []), str(path), *extra]


#: a saturated 115200-baud line's time per byte (11 bits), the bus capture's clock
BYTE_TIME = 11 / 115200


def _bus_capture(data: bytes, path: Path, step: int) -> Path:
    """``data`` as a capture of one RTU bus (pcap, link type 147), a record per
    ``step`` bytes at the times a saturated 115200-baud line delivers them (cached)."""
    from mbmon.io.pcap import PcapWriter

    if not path.exists():
        with PcapWriter(path, 147) as w:
            for i in range(0, len(data), step):
                w.write(1_700_000_000.0 + (i + step) * BYTE_TIME, data[i : i + step])
    return path


def read_rows(data: bytes, cache: Path, step: int = 4096, *, bus: bool = False) -> None:
    """``mbmon read --rtu-raw`` end to end, core and pure, in the same run: MB/s of the
    child's CPU, whole and marginal (start-up cancels out). ``bus``: ``mbmon read`` of
    the dump as a capture of an RTU bus (USER0, records of ``step`` bytes) instead."""
    from read_throughput import measure

    n = len(data)
    small = _part(data, cache, n // 5)
    what = "read --rtu-raw"
    if bus:
        small = _bus_capture(data[: n // 5], small.with_suffix(".pcap"), step)
        cache = _bus_capture(data, cache.with_suffix(".pcap"), step)
        what = "read BUS.pcap"
    print(f"{what} end to end ({n / 1e6:.1f} MB and its first fifth; CPU of the child):")
    for label, extra in READS:
        cpus: dict[str, float] = {}
        for path_label, pure in (("core", False), ("pure", True)):
            big = measure("", _read_cmd(cache, extra, pure, not bus), None)
            little = measure("", _read_cmd(small, extra, pure, not bus), None)
            if big.rc or little.rc:
                print(f"  {label} {path_label}: exit {big.rc} / {little.rc}")
                continue
            whole = big.user + big.sys
            margin = whole - (little.user + little.sys)
            cpus[path_label] = whole
            rate = (n - n // 5) / margin / 1e6 if margin > 0 else float("inf")
            print(
                f"  {what} {label:<7} {path_label}: {whole:6.2f} s CPU, "
                f"{n / whole / 1e6:6.2f} MB/s whole, {rate:6.2f} MB/s marginal"
                f"  (start-up and the first fifth {little.user + little.sys:.2f} s)"
            )
        if len(cpus) == 2:
            print(f"  {what} {label:<7} core {cpus['pure'] / cpus['core']:.1f}x pure by CPU")


def read_callgrind(data: bytes, cache: Path) -> None:
    """Callgrind instructions per byte of ``read --rtu-raw``, marginal:
    (I(400 KB) - I(100 KB)) / 300,000, core and pure."""
    import os
    import shutil
    import subprocess

    if not shutil.which("valgrind"):
        print("  (valgrind is missing: no instruction counts)")
        return
    lo, hi = _part(data, cache, 100_000), _part(data, cache, 400_000)
    out = OUT / "rtu-callgrind.out"
    for label, extra in READS:
        for path_label, pure in (("core", False), ("pure", True)):
            counts = []
            for path in (lo, hi):
                cmd = _read_cmd(path, extra, pure)
                if cmd[0] == "env":
                    cmd = cmd[2:]
                env = dict(os.environ, PYTHONHASHSEED="0")
                if pure:
                    env["MBMON_NO_EXTENSIONS"] = "1"
                subprocess.run(
                    ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", *cmd],
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False, env=env,
                )  # fmt: skip
                text = out.read_text(errors="replace")
                out.unlink()
                counts.append(
                    int(
                        next(ln for ln in text.splitlines() if ln.startswith("summary:")).split()[1]
                    )
                )
            per = (counts[1] - counts[0]) / (400_000 - 100_000)
            print(
                f"  callgrind instructions per byte, read --rtu-raw {label} {path_label}: "
                f"{per:,.0f}"
            )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=float, default=10.0, help="dump size in MB (10)")
    ap.add_argument("--read", type=int, default=4096, help="bytes per read (4096)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--limit", type=int, help="feed only the first LIMIT bytes of the dump")
    ap.add_argument("--decoder-only", action="store_true", help="skip the pipeline runs")
    ap.add_argument(
        "--repeat", type=int, default=10, help="runs of the compiled framer's packed output (10)"
    )
    ap.add_argument(
        "--which",
        choices=("all", "pure", "core", "core-objects"),
        default="all",
        help="the decoders to run (one, under callgrind): the reference RtuDecoder, the "
        "compiled framer's packed output, or its Frame/Noise objects (all)",
    )
    ap.add_argument(
        "--read-cmd",
        dest="read_rows",
        action="store_true",
        help="mbmon read --rtu-raw end to end, core and pure, text/--json/-q (CPU of the child)",
    )
    ap.add_argument(
        "--bus-cmd",
        dest="bus_rows",
        action="store_true",
        help="mbmon read of the dump as a capture of an RTU bus (USER0, a record per read, "
        "a 115200-baud line's times), core and pure, text/--json/-q (CPU of the child)",
    )
    ap.add_argument(
        "--read-callgrind",
        action="store_true",
        help="callgrind instructions per byte of read --rtu-raw, core and pure (marginal)",
    )
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
        f"{len(chunks)} reads of {step} bytes; {core.status()}"
    )
    want = {"pure", "core", "core-objects"} if args.which == "all" else {args.which}
    compiled = core.rtu_decline(None) is None
    if not compiled and want != {"pure"}:
        print(f"compiled RTU framer: not run ({core.rtu_decline(None)})")
    seen: dict[str, tuple[int, int, float]] = {}
    if "pure" in want:
        seen["pure"] = _timed(
            "RtuDecoder (reference) alone",
            n,
            lambda: _objects(RtuDecoder(stream, Direction.BUS), chunks),
        )
    if "core" in want and compiled:
        seen["core"] = _timed(
            "RtuCore (compiled), packed output",
            n,
            lambda: _packed(core.rtu_decoder(stream, Direction.BUS), chunks),
            repeat=args.repeat,
        )
    if "core-objects" in want and compiled:
        seen["core-objects"] = _timed(
            "RtuCore (compiled), Frame/Noise objects",
            n,
            lambda: _objects(core.rtu_decoder(stream, Direction.BUS), chunks),
        )
    counts = {(f, nb) for f, nb, _ in seen.values()}
    if len(counts) > 1:
        print(f"THE DECODERS DISAGREE: {seen}")
        return 1
    for f, _nb in counts:
        found = _found(f, frames_written) if args.limit is None else "part of the dump"
        print(f"frames: {found}")
    if "pure" in seen and "core" in seen:
        ratio = seen["pure"][2] / seen["core"][2]
        rate = n / seen["core"][2] / 1e6
        print(
            f"compiled framer {ratio:.0f}x the reference by CPU; target >= {TARGET} MB/s "
            f"(CPU): {'met' if rate >= TARGET else 'NOT met'}"
        )
    if args.read_rows:
        read_rows(data, cache)
    if args.bus_rows:
        read_rows(data, cache, step, bus=True)
    if args.read_callgrind:
        read_callgrind(data, cache)
    if args.decoder_only:
        return 0
    runs = [("reference decoder", True)] + ([("compiled framer", False)] if compiled else [])
    for label, pure in runs:
        _timed(
            f"Pipeline (decoder + pairing + records), {label}",
            n,
            lambda pure=pure: _pipeline(chunks, stream, pure),
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
