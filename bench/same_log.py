"""Whole log files of two trees, byte for byte: ``read CAPTURE -q -w x.mcap`` written by
this tree and by another one (core and forced pure), compared after masking what
depends on the wall clock (the metadata's ``started``, a profile attachment's log
time and the CRCs over them).

    python bench/same_log.py --against /tmp/old captures/*.pcap
    python bench/same_log.py --against /tmp/old --no-pure bench/out/real_polling_1000000_*.pcap

Each tree runs ``python -m mbmon`` with itself first on ``PYTHONPATH``, from one
scratch directory, so both record the same command line. A capture whose name holds
``hrss`` is read with ``--profile hrss --robot 192.168.0.10`` (a log with an
attachment). Exit status 1 when any pair differs.

What this script owns: the before/after check of a change that must not move a byte
of the log (docs/performance.md, "The block's hand-over and the writes").
"""

from __future__ import annotations

import argparse
import os
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MAGIC = b"\x89MCAP0\r\n"
OP_FOOTER, OP_ATTACHMENT, OP_ATTACHMENT_INDEX, OP_METADATA = 0x02, 0x09, 0x0A, 0x0C


def _zero(buf: bytearray, at: int, n: int) -> None:
    buf[at : at + n] = bytes(n)


def _mask_metadata(buf: bytearray, body: int) -> None:
    name_len = struct.unpack_from("<I", buf, body)[0]
    at = body + 4 + name_len + 4  # the map's pairs
    end = at + struct.unpack_from("<I", buf, at - 4)[0]
    while at < end:
        klen = struct.unpack_from("<I", buf, at)[0]
        key = bytes(buf[at + 4 : at + 4 + klen])
        at += 4 + klen
        vlen = struct.unpack_from("<I", buf, at)[0]
        if key == b"started":
            _zero(buf, at + 4, vlen)
        at += 4 + vlen


def masked(data: bytes) -> bytes:
    """``data`` (a finished MCAP file) with its wall-clock members zeroed."""
    buf = bytearray(data)
    assert buf[:8] == MAGIC and buf[-8:] == MAGIC, "not a finished MCAP file"
    at = 8
    while at < len(buf) - 8:
        op, n = struct.unpack_from("<BQ", buf, at)
        body = at + 9
        if op == OP_METADATA:
            _mask_metadata(buf, body)
        elif op == OP_ATTACHMENT:
            _zero(buf, body, 8)  # log_time (the run's start)
            _zero(buf, body + n - 4, 4)  # the CRC over it
        elif op == OP_ATTACHMENT_INDEX:
            _zero(buf, body + 16, 8)  # log_time
        elif op == OP_FOOTER:
            _zero(buf, body + 16, 4)  # the summary's CRC (over the attachment index)
        at = body + n
    return bytes(buf)


def log_of(tree: Path, capture: Path, scratch: Path, *, pure: bool) -> tuple[bytes, int]:
    """``tree``'s log of ``capture`` (masked) and the run's exit status."""
    env = dict(os.environ, PYTHONPATH=str(tree), TZ="UTC")
    if pure:
        env["MBMON_NO_EXTENSIONS"] = "1"
    extra = ["--profile", "hrss", "--robot", "192.168.0.10"] if "hrss" in capture.name else []
    log = scratch / "x.mcap"
    log.unlink(missing_ok=True)
    done = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", str(capture), *extra, "-q", "-w", log.name],
        cwd=scratch, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, check=False,
    )  # fmt: skip
    if done.returncode != 0:
        sys.stderr.write(done.stderr.decode(errors="replace"))
    return masked(log.read_bytes()), done.returncode


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("captures", nargs="+", type=Path)
    ap.add_argument("--against", type=Path, required=True, help="the other tree (core built)")
    ap.add_argument("--no-pure", action="store_true", help="the compiled core's logs only")
    args = ap.parse_args()
    differ = 0
    with tempfile.TemporaryDirectory(prefix="same_log_") as tmp:
        scratch = Path(tmp)
        for capture in args.captures:
            capture = capture.resolve()
            for pure in (False,) if args.no_pure else (False, True):
                mine = log_of(REPO, capture, scratch, pure=pure)
                theirs = log_of(args.against.resolve(), capture, scratch, pure=pure)
                same = mine == theirs
                differ += not same
                what = "pure" if pure else "core"
                verdict = "same" if same else "DIFFERENT"
                print(f"{verdict:9s} {what}  {len(mine[0]):>11,d} bytes  {capture.name}")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
