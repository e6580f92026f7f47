"""Mutated observation pipes through the core's chunk entry: it never crashes and never
raises (what it does not cover hands the run over), and it writes what the parent's
reference wiring writes for the same reads and ticks (harness: ``core_diff.py``).

Mutations work on the chunks' bytes (flipped, a field set to an extreme, cut,
doubled: the client's and the upstream's traffic is untrusted), on the chunks'
order (swapped, dropped, repeated), on their times (backwards, far ahead) and on
the cuts of the pipe and the ticks; the pipe's own record heads, streams and
events stay as the forwarding process writes them. ``MBMON_FUZZ_RUNS`` (default 300; a tenth of it
here, each case runs two hubs), ``MBMON_FUZZ_DIFF=0`` (only memory safety: the
AddressSanitizer run in CI) and ``MBMON_FUZZ_SEED`` as in the core's other fuzz
tests.
"""

from __future__ import annotations

import os
import random
import struct

import pytest

from mbmon.protocol.pdu import encode_exception
from tests.core.gen import every_function_pair
from tests.proxy import core_diff as cd
from tests.proxy.test_proxy_e2e import adu

try:
    from mbmon.core import _load

    _WHY = _load()
except ImportError as exc:  # pragma: no cover
    _WHY = str(exc)

pytestmark = pytest.mark.skipif(
    _WHY is not None and os.environ.get("MBMON_REQUIRE_CORE") != "1",
    reason=f"the compiled core is not built: {_WHY}",
)

RUNS = max(1, int(os.environ.get("MBMON_FUZZ_RUNS", "300")) // 10)
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")

#: a record of the pipe before it is written: ("chunk", key, direction, ts, bytes)
#: or ("raw", bytes) for the other records (streams, events)
Rec = tuple


def _seed(own: bool) -> list[Rec]:
    """Two clients, every function code; ``own``: a refusal on the proxy's own stream."""
    recs: list[Rec] = [("raw", cd.client(0, 100.0, 40000)), ("raw", cd.client(2, 100.0, 40001))]
    t = 100.0
    for tid, (req, resp) in enumerate(every_function_pair()):
        key = 2 * (tid & 1)
        t += 0.05
        recs.append(("chunk", key, cd.C2S, t, adu(tid, 1 + tid % 3, req)))
        recs.append(("chunk", key, cd.S2C, t + 0.01, adu(tid, 1 + tid % 3, resp)))
    if own:
        recs.append(("chunk", 1, cd.C2S, t + 0.1, adu(99, 1, bytes.fromhex("0600010002"))))
        recs.append(("chunk", 1, cd.S2C, t + 0.1, adu(99, 1, encode_exception(6, 1))))
    recs.append(("raw", cd.event(t + 0.2, 0, "disconnect", {"how": "fin", "by": "client"})))
    recs.append(("raw", cd.event(t + 0.3, 2, "disconnect", {"how": "reset", "by": "upstream"})))
    return recs


def _mutate_bytes(data: bytes, rng: random.Random) -> bytes:
    buf = bytearray(data)
    if not buf:
        return data
    how = rng.randrange(5)
    if how == 0:
        for _ in range(rng.randint(1, 4)):
            buf[rng.randrange(len(buf))] ^= 1 << rng.randrange(8)
    elif how == 1:
        at = rng.randrange(max(1, len(buf) - 2))
        value = rng.choice([0, 1, 0xFF, 0xFFFF, len(buf)])
        buf[at : at + 2] = struct.pack(">H", value)[: len(buf[at : at + 2])]
    elif how == 2:
        del buf[rng.randrange(len(buf)) :]
    elif how == 3:
        a = rng.randrange(len(buf))
        del buf[a : a + rng.randint(1, 16)]
    else:
        a = rng.randrange(len(buf))
        buf[a:a] = buf[a : a + rng.randint(1, 16)]
    return bytes(buf)


def _mutate(recs: list[Rec], rng: random.Random) -> list[Rec]:
    out = list(recs)
    for _ in range(rng.randint(1, 4)):
        i = rng.randrange(len(out))
        rec = out[i]
        how = rng.randrange(6)
        if how <= 1 and rec[0] == "chunk":
            out[i] = (*rec[:4], _mutate_bytes(rec[4], rng))
        elif how == 2 and rec[0] == "chunk":
            out[i] = (*rec[:3], rec[3] + rng.choice([-50.0, -0.5, 3.0, 700.0]), rec[4])
        elif rec[0] != "chunk":  # streams and events stay where the child puts them
            continue
        elif how == 3 and i + 1 < len(out) and out[i + 1][0] == "chunk":
            out[i], out[i + 1] = out[i + 1], out[i]
        elif how == 4:
            del out[i]
        else:
            out.insert(i, rec)
    return out


def _steps(recs: list[Rec], rng: random.Random) -> list[cd.Step]:
    data = b"".join(
        r[1] if r[0] == "raw" else cd.chunk(r[1], r[2], r[3], r[4]) for r in recs
    )  # fmt: skip
    steps: list[cd.Step] = []
    pos = 0
    while pos < len(data):
        n = rng.choice([1, 7, 64, 500, 1 << 16])
        steps.append(data[pos : pos + n])
        pos += n
        if rng.random() < 0.2:
            steps.append(100.0 + rng.choice([0.5, 2.0, 6.0, 900.0]))
    steps.append(2000.0)
    return steps


def test_mutated_pipes() -> None:
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed)
    bases = [_seed(False), _seed(True)]
    covered = 0
    for case in range(RUNS):
        steps = _steps(_mutate(bases[case % 3 == 2], rng), rng)
        as_json = bool(case & 1)
        try:
            got, why = cd.core(steps, as_json=as_json)
        except Exception as exc:  # the seed and case make the failure repeatable
            raise AssertionError(f"seed {seed} case {case}: the core raised {exc!r}") from exc
        covered += why is None
        if DIFF:
            want = cd.reference(steps, as_json=as_json)
            assert got == want, (
                f"seed {seed} case {case}: the core and the reference differ ({why})"
            )
    if RUNS >= 10:
        assert covered, "every mutation was handed over: the core ran on none of them"
