"""Mutated HRSS captures read with ``--profile hrss`` (and a data-only profile of every
register kind) through the core: it never crashes, never raises but to decline, and
where it runs it writes what the reference pipeline writes with the same profile.

The mutations are :mod:`test_core_fuzz`'s on the capture's bytes (most end in a
decline: a gap, noise) and, so that the profile path runs on odd PDUs, mutations of the
PDUs themselves written as well-formed TCP. ``MBMON_FUZZ_RUNS`` (a tenth of it here,
at least 30), ``MBMON_FUZZ_DIFF=0`` and ``MBMON_FUZZ_SEED`` work as there (CI's
AddressSanitizer run reads these with ``MBMON_FUZZ_DIFF=0``).
"""

from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path

from core_diff import require_core
from test_core_fuzz import mutate
from test_core_profile import KINDS, hrss_session_steps, kinds_steps, reference, write_capture

from mbmon import core
from mbmon.format import View
from mbmon.semantics.annotate import annotator_for
from mbmon.timefmt import TimeFormat

Step = tuple[float, int, int, bytes | None, bytes | None]
RUNS = max(int(os.environ.get("MBMON_FUZZ_RUNS", "300")) // 10, 30)
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")


def _core_run(data: bytes, specs: list[str], as_json: bool) -> tuple[bytes, str | None]:
    chunks: list[bytes] = []
    run = core.read_buffer(
        data,
        ports=frozenset({502}),
        timeout=1.0,
        view=View(time_format=TimeFormat("a")),
        as_json=as_json,
        write=chunks.append,
        annotator=annotator_for(specs),
    )
    if run.declined is not None:
        assert not chunks
    return b"".join(chunks), run.declined


def mutate_pdus(steps: list[Step], rng: random.Random) -> list[Step]:
    """Some PDUs with flipped bits, cut, lengthened or swapped for another step's."""
    out = []
    for t, client, unit, req, resp in steps:
        if rng.random() < 0.15:
            which = rng.randrange(2)
            pdu = bytearray((req, resp)[which] or b"\x03")
            how = rng.randrange(4)
            if how == 0:
                pdu[rng.randrange(len(pdu))] ^= 1 << rng.randrange(8)
            elif how == 1 and len(pdu) > 1:
                del pdu[rng.randrange(1, len(pdu)) :]
            elif how == 2:
                pdu += bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
            else:
                pdu = bytearray(rng.choice(steps)[3 + rng.randrange(2)] or b"\x04")
            if which == 0:
                req = bytes(pdu)
            else:
                resp = bytes(pdu)
        out.append((t, client, unit, req, resp))
    return out


def test_mutated_captures_with_profiles() -> None:
    require_core()
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed)
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        kinds = base / "kinds.toml"
        kinds.write_text(KINDS, encoding="utf-8")
        steps = hrss_session_steps()
        plans = [(steps[:120], ["hrss"]), (kinds_steps(seed)[:60], [str(kinds)])]
        seeds = [
            (write_capture(base / "hrss.pcap", steps).read_bytes(), ["hrss"]),
            (write_capture(base / "short.pcap", steps[:60]).read_bytes(), ["hrss"]),
            (write_capture(base / "kinds.pcap", kinds_steps(seed)[:80]).read_bytes(), [str(kinds)]),
        ]
        ran = 0
        for case in range(RUNS):
            if rng.random() < 0.5:
                data, specs = rng.choice(seeds)
                data = mutate(data, rng)
                if rng.random() < 0.3:
                    data = mutate(data, rng)
            else:
                steps, specs = rng.choice(plans)
                data = write_capture(base / "p.pcap", mutate_pdus(steps, rng)).read_bytes()
            as_json = bool(case & 1)
            try:
                got, why = _core_run(data, specs, as_json)
            except Exception as exc:  # the seed and case make the failure repeatable
                raise AssertionError(f"seed {seed} case {case}: the core raised {exc!r}") from exc
            if why is not None:
                continue
            ran += 1
            if DIFF:
                path = base / "m.pcap"
                path.write_bytes(data)
                want, _ = reference(path, specs, as_json=as_json, timeout=1.0)
                assert got == want, f"seed {seed} case {case}: the core and the reference differ"
        assert ran, "the core declined every mutation: the fuzz test exercised nothing"
