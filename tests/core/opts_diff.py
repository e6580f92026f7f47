"""The differential harness of ``read``'s options: one command line run in this
process by ``mbmon read`` with the compiled core and again forced pure (the core
made unavailable, as ``MBMON_NO_EXTENSIONS=1`` makes it), stdout's bytes, stderr's
text and the exit status compared.

``read_both`` gives both runs and which path the first took (``--debug-core``'s
line, taken out of stderr before the comparison).
"""

from __future__ import annotations

import io
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from mbmon import core


@dataclass
class Run:
    status: int
    out: bytes
    err: str
    #: what --debug-core said (its lines, "core: ...")
    core: list[str]


@contextmanager
def _pure() -> Iterator[None]:
    """The core unavailable in this process for a while (what the pure build is)."""
    core._load()
    saved = core._UNAVAILABLE
    core._UNAVAILABLE = "forced pure by the test"
    try:
        yield
    finally:
        core._UNAVAILABLE = saved


def read_run(args: list[str | Path], *, pure: bool = False) -> Run:
    """``mbmon read ARGS --debug-core`` in this process: its exit status, stdout's bytes,
    stderr without the ``core:`` lines, and those lines."""
    from mbmon.cli import build_parser
    from mbmon.commands.common import UsageError

    parsed = build_parser().parse_args(["read", "--debug-core", *map(str, args)])
    raw = io.BytesIO()
    out = io.TextIOWrapper(raw, encoding="utf-8", errors="backslashreplace", write_through=True)
    err = io.StringIO()
    saved = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = out, err  # type: ignore[assignment]
    try:
        with _pure() if pure else _nothing():
            try:
                status = parsed.func(parsed)
            except UsageError as exc:
                print(f"usage: {exc}", file=sys.stderr)
                status = 2
        out.flush()
    finally:
        sys.stdout, sys.stderr = saved
    lines = err.getvalue().splitlines(keepends=True)
    said = [line[7:].rstrip("\n") for line in lines if line.startswith("mbmon: core: ")]
    rest = "".join(line for line in lines if not line.startswith("mbmon: core: "))
    return Run(status, raw.getvalue(), rest, said)


@contextmanager
def _nothing() -> Iterator[None]:
    yield


def read_both(args: list[str | Path]) -> tuple[Run, Run]:
    """The same ``read`` with the core (first) and forced pure (second)."""
    return read_run(args), read_run(args, pure=True)


def ran_core(run: Run) -> bool:
    """Whether the compiled core read the input of ``run``."""
    return "core: the compiled core read the input" in run.core


def assert_same(args: list[str | Path], *, covered: bool | None = None) -> Run:
    """Core and forced pure agree byte for byte (stdout, stderr, exit status);
    ``covered`` True/False: the core must run / must decline. The core's run."""
    fast, pure = read_both(args)
    if covered is True:
        assert ran_core(fast), f"the core declined {args}: {fast.core}"
    elif covered is False:
        assert not ran_core(fast), f"the core ran on {args}"
    if fast.out != pure.out:
        a_lines, b_lines = fast.out.splitlines(), pure.out.splitlines()
        for i, (a, b) in enumerate(zip(a_lines, b_lines, strict=False)):
            assert a == b, f"{args}: line {i}"
        assert len(a_lines) == len(b_lines), f"{args}: {len(a_lines)} != {len(b_lines)} lines"
    assert fast.err == pure.err, args
    assert fast.status == pure.status, args
    return fast
