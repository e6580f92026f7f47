"""The differential harness: one capture through the compiled core and through the
reference pipeline (wired as ``mbmon read`` wires it), both in this process.

``reference`` and ``with_core`` give ``(stdout bytes, summary text)``; ``with_core``
also says why the core declined (``None``: it ran). A decline must have written
nothing; the suites then compare nothing more (the reference runs instead).
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import pytest

from mbmon import core
from mbmon.format import View
from mbmon.hub import Hub
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.semantics.annotate import annotator_for
from mbmon.sinks.console import ConsoleListener
from mbmon.sinks.select import Selection
from mbmon.sinks.summary import Summary
from mbmon.sources.pcapfile import CaptureConfig, CaptureError, read_capture
from mbmon.timefmt import TimeFormat

ROOT = Path(__file__).resolve().parents[2]
# ../shared from the repository's root (a worktree one level deeper looks one further up)
REAL = next(
    (
        base / "shared" / "captures" / "real"
        for base in (ROOT.parent, ROOT.parent.parent)
        if (base / "shared" / "captures" / "real").is_dir()
    ),
    ROOT.parent / "shared" / "captures" / "real",
)


def require_core() -> None:
    """Skip (or fail, when CI demands the core: MBMON_REQUIRE_CORE=1) without the core."""
    if core.available():
        return
    if os.environ.get("MBMON_REQUIRE_CORE", "") not in ("", "0"):
        pytest.fail(f"the compiled core is required here: {core.status()}")
    pytest.skip(core.status())


def reference(
    path: str | Path,
    *,
    as_json: bool,
    ports: frozenset[int] = frozenset({502}),
    timeout: float = 1.0,
    detect: bool = False,
    specs: list[str] | None = None,
) -> tuple[bytes, str]:
    """``mbmon read`` by the Python pipeline: stdout's bytes and the summary's text
    (``specs``: the ``--profile`` values, none by default)."""
    raw = io.BytesIO()
    out = io.TextIOWrapper(raw, encoding="utf-8", errors="backslashreplace", write_through=True)
    view = View(time_format=TimeFormat("a"))
    annotator = annotator_for(specs) if specs else None
    hub = Hub(Pipeline(annotator, PipelineConfig(timeout=timeout)))
    summary = Summary(None)
    hub.add_listener(Selection([ConsoleListener(out, view, as_json=as_json)], view))
    hub.add_listener(summary)
    try:
        hub.run_items(read_capture(path, CaptureConfig(tcp_ports=ports, detect=detect)))
    except CaptureError as exc:
        return b"", f"error: {exc}"
    hub.close()
    out.flush()
    return raw.getvalue(), summary.text(timed=True)


def with_core(
    path: str | Path,
    *,
    as_json: bool,
    ports: frozenset[int] = frozenset({502}),
    timeout: float = 1.0,
    detect: bool = False,
    specs: list[str] | None = None,
) -> tuple[bytes, str, str | None]:
    """``mbmon read`` by the compiled core: stdout's bytes, the summary, the decline
    (``specs``: the ``--profile`` values; a profile the core declines is that decline)."""
    annotator = annotator_for(specs) if specs else None
    if annotator is not None:
        why = core.decline_for_profile(annotator)
        if why is not None:
            return b"", "", why
    chunks: list[bytes] = []
    run = core.read_file(
        str(path),
        ports=ports,
        timeout=timeout,
        view=View(time_format=TimeFormat("a")),
        as_json=as_json,
        write=chunks.append,
        detect=detect,
        annotator=annotator,
    )
    if run.declined is not None:
        assert not chunks, "a decline wrote bytes"
        return b"", "", run.declined
    summary = Summary(None)
    core.fill_summary(summary, run.counts)
    return b"".join(chunks), summary.text(timed=True), None


def assert_same(path: str | Path, *, covered: bool | None = None, **kw: object) -> str | None:
    """Core and reference agree byte for byte, text and JSON (or the core declined);
    ``covered`` True/False: the core must run / must decline. Returns the decline."""
    why = None
    for as_json in (False, True):
        got, got_summary, why = with_core(path, as_json=as_json, **kw)  # type: ignore[arg-type]
        if covered is True:
            assert why is None, f"the core declined {path}: {why}"
        elif covered is False:
            assert why is not None, f"the core ran on {path}"
        if why is not None:
            continue
        want, want_summary = reference(path, as_json=as_json, **kw)  # type: ignore[arg-type]
        if got != want:
            got_lines, want_lines = got.splitlines(), want.splitlines()
            for i, (a, b) in enumerate(zip(got_lines, want_lines, strict=False)):
                assert a == b, f"{path} json={as_json} line {i}"
            assert len(got_lines) == len(want_lines), f"{path} json={as_json}: line count"
        assert got == want
        assert got_summary == want_summary
    return why
