"""Mutated captures through the core under drawn options (``-t``, ``--robot``, the
filters, ``--grep``, ``-c``, ``-q``, ``--json``): never a crash, never an exception but
a decline, and where the core runs, ``mbmon read``'s bytes forced pure.

``MBMON_FUZZ_RUNS`` sets how many mutations (default 100, a fifth of them compared
with the reference: each comparison is two whole ``read`` runs); ``MBMON_FUZZ_DIFF=0``
compares none (CI's AddressSanitizer run: memory safety of the selection's paths —
lines written, tested and taken back, the run ended mid-buffer by ``-c``).
"""

from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path

from core_diff import require_core
from opts_diff import assert_same
from test_core_fuzz import _seeds, mutate

from mbmon import core

RUNS = int(os.environ.get("MBMON_FUZZ_RUNS", "100"))
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")

_OPTIONS = (
    ["--fc", "3,4"],
    ["--fc", "16", "-c", "2"],
    ["--unit", "1", "--address", "100-200"],
    ["--grep", "read", "-c", "3"],
    ["--grep", "→"],
    ["--since", "+0.01s", "--until", "+2s", "-t", "r"],
    ["-c", "1"],
    ["-c", "5", "-q"],
    ["-q", "--grep", "no response", "-c", "1"],
    ["--robot", "127.0.0.1", "-t", "ud"],
    ["-t", "e", "--address", "0-0"],
    ["--where", "exception or latency > 1ms", "-c", "4"],
)


def _drawn(rng: random.Random) -> list[str]:
    args = list(rng.choice(_OPTIONS))
    if rng.random() < 0.5:
        args.append("--json")
    return args


_PARSER: list[object] = []


def _core_only(data: bytes, args: list[str]) -> bool:
    """The core alone on ``data`` with ``args`` (read's own options and filter): whether
    it ran (did not decline)."""
    from mbmon.cli import build_parser
    from mbmon.commands.outputs import view_and_filter

    if not _PARSER:
        _PARSER.append(build_parser())
    parsed = _PARSER[0].parse_args(["read", "x.pcap", *args])  # type: ignore[attr-defined]
    view, flt = view_and_filter(parsed)
    chunks: list[bytes] = []
    run = core.read_buffer(
        data,
        ports=frozenset({502}),
        timeout=1.0,
        view=view,
        as_json=parsed.json,
        write=None if parsed.quiet else chunks.append,
        flt=flt,
        count=parsed.count,
    )
    if run.declined is not None:
        assert not chunks
    return run.declined is None


def test_mutated_captures_under_options() -> None:
    require_core()
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26"))
    rng = random.Random(seed)
    with tempfile.TemporaryDirectory() as tmp:
        seeds = _seeds(Path(tmp))
        ran = 0
        for case in range(RUNS):
            data = mutate(rng.choice(seeds), rng)
            args = _drawn(rng)
            try:
                ran += _core_only(data, args)
            except Exception as exc:  # the seed and case make the failure repeatable
                raise AssertionError(f"seed {seed} case {case} {args}: {exc!r}") from exc
            if DIFF and case % 5 == 0:
                path = Path(tmp) / "m.pcap"
                path.write_bytes(data)
                assert_same([path, *args])
        if RUNS >= 100:
            assert ran, "the core declined every mutation: the fuzz test exercised nothing"
