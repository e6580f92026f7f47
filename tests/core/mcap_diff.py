"""The differential harness for logs: ``read -w x.mcap`` of one capture through the
compiled core and through the reference pipeline (wired as ``mbmon read`` wires
them: the log first, then the console, then the summary), both in this process.

What must be equal: every message (channel topic, sequence, log and publish time,
payload bytes) in file order, the summary the ``mcap`` reader gives (statistics but
for the chunk count, which follows wall-clock flushes; schemas; channels),
the metadata but for the wall-clock start, the console's bytes and the summary's
text. A decline must not have opened the log.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from mbmon import core
from mbmon.format import View
from mbmon.hub import Hub
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.sinks.base import SinkContext
from mbmon.sinks.console import ConsoleListener
from mbmon.sinks.mcap import McapSink
from mbmon.sinks.select import Selection
from mbmon.sinks.summary import Summary
from mbmon.sources.pcapfile import CaptureConfig, CaptureError, read_capture
from mbmon.timefmt import TimeFormat


def _context(path: Path, view: View, timeout: float) -> SinkContext:
    return SinkContext(
        view=view,
        command_line=["mbmon", "read", str(path), "-w", "x.mcap"],
        source=str(path),
        profiles=[],
        profile_specs=[],
        timeout=timeout,
        baud=None,
    )


def reference_log(
    path: Path,
    log: Path,
    *,
    as_json: bool = False,
    quiet: bool = False,
    ports: frozenset[int] = frozenset({502}),
    timeout: float = 1.0,
    detect: bool = False,
) -> tuple[bytes, str]:
    """``mbmon read PATH -w LOG`` by the Python pipeline: stdout's bytes and the summary."""
    raw = io.BytesIO()
    out = io.TextIOWrapper(raw, encoding="utf-8", errors="backslashreplace", write_through=True)
    view = View(time_format=TimeFormat("a"))
    hub = Hub(Pipeline(None, PipelineConfig(timeout=timeout)))
    summary = Summary(None)
    hub.add_listener(McapSink(log, _context(path, view, timeout)))
    if not quiet:
        hub.add_listener(Selection([ConsoleListener(out, view, as_json=as_json)], view))
    hub.add_listener(summary)
    try:
        hub.run_items(read_capture(path, CaptureConfig(tcp_ports=ports, detect=detect)))
    except CaptureError as exc:
        hub.close()
        return b"", f"error: {exc}"
    hub.close()
    out.flush()
    return raw.getvalue(), summary.text(timed=True)


def core_log(
    path: Path,
    log: Path,
    *,
    as_json: bool = False,
    quiet: bool = False,
    ports: frozenset[int] = frozenset({502}),
    timeout: float = 1.0,
    detect: bool = False,
) -> tuple[bytes, str, str | None]:
    """``mbmon read PATH -w LOG`` by the compiled core: stdout, the summary, the decline.
    A decline must come before the log was opened."""
    chunks: list[bytes] = []
    view = View(time_format=TimeFormat("a"))
    opened: list[McapSink] = []

    def open_log() -> McapSink:
        sink = McapSink(log, _context(path, view, timeout))
        opened.append(sink)
        return sink

    run = core.read_file(
        str(path),
        ports=ports,
        timeout=timeout,
        view=view,
        as_json=as_json,
        write=None if quiet else chunks.append,
        detect=detect,
        log=open_log,
    )
    if run.declined is not None:
        assert not chunks, "a decline wrote bytes"
        assert not opened, "a decline opened the log"
        return b"", "", run.declined
    assert len(opened) == 1 and not run.interrupted
    summary = Summary(None)
    core.fill_summary(summary, run.counts)
    return b"".join(chunks), summary.text(timed=True), None


def log_contents(log: Path) -> dict[str, Any]:
    """What two logs of the same run must share (see the module docstring)."""
    with open(log, "rb") as f:
        reader = make_reader(f)
        messages = [
            (channel.topic, m.sequence, m.log_time, m.publish_time, m.data)
            for _schema, channel, m in reader.iter_messages(log_time_order=False)
        ]
        summary = reader.get_summary()
        assert summary is not None, f"{log}: not finished"
        stats = summary.statistics
        assert stats is not None
        metadata = [dict(m.metadata) for m in reader.iter_metadata()]
        attachments = [(a.name, a.media_type, a.data) for a in reader.iter_attachments()]
    for m in metadata:
        m.pop("started", None)  # the wall clock when the log was opened
    topic_of = {cid: ch.topic for cid, ch in summary.channels.items()}
    return {
        "messages": messages,
        "count": stats.message_count,
        "per_topic": {topic_of[c]: n for c, n in stats.channel_message_counts.items()},
        "span": (stats.message_start_time, stats.message_end_time),
        "counts": (stats.schema_count, stats.channel_count, stats.attachment_count),
        "metadata_count": stats.metadata_count,
        "schemas": sorted((s.id, s.name, s.encoding, s.data) for s in summary.schemas.values()),
        "channels": sorted(
            (c.id, c.topic, c.message_encoding, c.schema_id) for c in summary.channels.values()
        ),
        "metadata": metadata,
        "attachments": attachments,
    }


def assert_same_log(path: Path, tmp: Path, *, covered: bool | None = None, **kw: Any) -> str | None:
    """Core and reference write the same log (and the same console and summary) for
    ``read PATH -w x.mcap``, quiet and with text and JSON on the console, or the core
    declined without opening the log. ``covered``: must run / must decline."""
    why = None
    for n, console in enumerate(({"quiet": True}, {"as_json": False}, {"as_json": True})):
        got_log, want_log = tmp / f"core{n}.mcap", tmp / f"ref{n}.mcap"
        got, got_summary, why = core_log(path, got_log, **console, **kw)
        if covered is True:
            assert why is None, f"the core declined {path}: {why}"
        elif covered is False:
            assert why is not None, f"the core ran on {path}"
        if why is not None:
            assert not got_log.exists(), "a declined input touched the log"
            return why
        want, want_summary = reference_log(path, want_log, **console, **kw)
        got_c, want_c = log_contents(got_log), log_contents(want_log)
        for i, (a, b) in enumerate(zip(got_c["messages"], want_c["messages"], strict=False)):
            assert a == b, f"{path} {console}: message {i}"
        assert got_c == want_c, f"{path} {console}"
        assert got == want, f"{path} {console}: console"
        assert got_summary == want_summary, f"{path} {console}: summary"
    return why
