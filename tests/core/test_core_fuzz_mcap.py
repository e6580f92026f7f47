"""Mutated captures read with ``-w x.mcap`` by the core: never a crash, never an
exception but a decline (and then the log was never opened); where the core runs,
the log is finished and reads back, and holds what the reference pipeline's holds.

The mutations and seeds are ``test_core_fuzz``'s. ``MBMON_FUZZ_RUNS`` / 10 cases
(each writes a log; at least 30); ``MBMON_FUZZ_DIFF=0`` skips the comparison with
the reference (the AddressSanitizer run in CI: only memory safety and a readable
log). The seed of each case is in the failure message.
"""

from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path

from core_diff import require_core
from mcap_diff import _context, log_contents, reference_log
from test_core_fuzz import _seeds, mutate

from mbmon import core
from mbmon.format import View
from mbmon.io.mcap.reader import McapLog
from mbmon.sinks.mcap import McapSink
from mbmon.timefmt import TimeFormat

RUNS = max(30, int(os.environ.get("MBMON_FUZZ_RUNS", "300")) // 10)
DIFF = os.environ.get("MBMON_FUZZ_DIFF", "1") not in ("", "0")


def _core_log(data: bytes, log: Path, source: Path) -> str | None:
    """The core's run with a log; the decline (then nothing was opened), or ``None``."""
    view = View(time_format=TimeFormat("a"))
    opened: list[McapSink] = []

    def open_log() -> McapSink:
        opened.append(McapSink(log, _context(source, view, 1.0)))
        return opened[-1]

    run = core.read_buffer(
        data,
        ports=frozenset({502}),
        timeout=1.0,
        view=view,
        as_json=False,
        write=None,
        log=open_log,
    )
    if run.declined is not None:
        assert not opened and not log.exists(), "a decline opened the log"
    return run.declined


def test_mutated_captures_to_a_log() -> None:
    require_core()
    seed = int(os.environ.get("MBMON_FUZZ_SEED", "26")) + 1
    rng = random.Random(seed)
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        seeds = _seeds(tmp)
        source, log, want = tmp / "m.pcap", tmp / "core.mcap", tmp / "ref.mcap"
        ran = 0
        for case in range(RUNS):
            data = mutate(rng.choice(seeds), rng)
            if rng.random() < 0.3:
                data = mutate(data, rng)
            log.unlink(missing_ok=True)
            try:
                why = _core_log(data, log, source)
            except Exception as exc:  # the seed and case make the failure repeatable
                raise AssertionError(f"seed {seed} case {case}: the core raised {exc!r}") from exc
            if why is not None:
                continue
            ran += 1
            with McapLog(log) as opened:
                assert opened.finished, f"seed {seed} case {case}: the log was not finished"
                assert sum(1 for _ in opened.messages()) == opened.status.messages
            if DIFF:
                source.write_bytes(data)
                reference_log(source, want, quiet=True)
                assert log_contents(log) == log_contents(want), (
                    f"seed {seed} case {case}: the core's log and the reference's differ"
                )
        assert ran, "the core declined every mutation: the fuzz test exercised nothing"
