"""The live differential harness: the same packets, in the same batches, with the same
ticks, through ``sniff``'s reference wiring (dissector → hub → pipeline → console)
and through the core's streaming entry (:class:`mbmon.core.live.LiveCore`), both in
this process. ``Step``s are batches of ``(ts, linktype, bytes)`` or hub ticks."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

from mbmon.format import View
from mbmon.hub import Hub
from mbmon.model import Event, EventKind
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.sinks.console import ConsoleListener
from mbmon.sinks.summary import Summary
from mbmon.sources.pcapfile import CaptureConfig
from mbmon.sources.sniff import dissect_batch, open_dissector
from mbmon.timefmt import TimeFormat

Packet = tuple[float, int, bytes]
#: a batch of packets, or a float: the hub ticks at that time
Step = list[Packet] | float


def packets_of(path: str | Path) -> list[Packet]:
    """Every record of a pcap or pcapng file as the capture thread gives them."""
    from scapy.utils import RawPcapNgReader, RawPcapReader

    out: list[Packet] = []
    with RawPcapReader(str(path)) as reader:  # a pcapng file opens as RawPcapNgReader
        ng = isinstance(reader, RawPcapNgReader)
        link = getattr(reader, "linktype", 1)
        for data, meta in reader:
            if ng:
                stamp = (meta.tshigh << 32) | meta.tslow
                ts = stamp / meta.tsresol
                out.append((ts, meta.linktype, bytes(data)))
            else:
                out.append((meta.sec + meta.usec / 1e6, link, bytes(data)))
    return out


def batches(packets: list[Packet], sizes: list[int]) -> list[Step]:
    """``packets`` cut into batches of the given sizes (cycled; at least one each)."""
    steps: list[Step] = []
    pos = i = 0
    while pos < len(packets):
        n = max(1, sizes[i % len(sizes)]) if sizes else len(packets)
        steps.append(packets[pos : pos + n])
        pos += n
        i += 1
    return steps


def _wire(as_json: bool, timeout: float) -> tuple[Hub, io.BytesIO, Any, Summary, View]:
    raw = io.BytesIO()
    out = io.TextIOWrapper(raw, encoding="utf-8", errors="backslashreplace", write_through=True)
    view = View(time_format=TimeFormat("a"))
    hub = Hub(Pipeline(None, PipelineConfig(timeout=timeout)), clock=lambda: 0.0)
    summary = Summary(None)
    hub.add_listener(ConsoleListener(out, view, as_json=as_json, live=True))
    hub.add_listener(summary)
    return hub, raw, out, summary, view


def _run(hub: Hub, steps: list[Step], feed: Any) -> None:
    for step in steps:
        if isinstance(step, float):
            hub.tick(step)
        else:
            hub.feed_items(feed(step))
    hub.finish()
    # the source's closing event, fed after the end as run_sources feeds it (at the
    # clock's time: here the last step's)
    end = max((s if isinstance(s, float) else s[-1][0] for s in steps if s), default=0.0)
    hub.feed(Event(end, None, EventKind.STATS, {"interface": "lo", "complete": True}))


def reference(
    steps: list[Step],
    *,
    as_json: bool,
    ports: frozenset[int] = frozenset({502}),
    timeout: float = 1.0,
) -> tuple[bytes, str]:
    """``sniff``'s reference wiring: stdout's bytes and the summary's text."""
    hub, raw, out, summary, _view = _wire(as_json, timeout)
    dissector = open_dissector(CaptureConfig(tcp_ports=ports), hub.new_stream)
    hub.add_ticker(dissector)
    _run(hub, steps, lambda batch: dissect_batch(dissector, batch))
    hub.close()
    out.flush()
    return raw.getvalue(), summary.text(timed=True)


def with_core(
    steps: list[Step],
    *,
    as_json: bool,
    ports: frozenset[int] = frozenset({502}),
    timeout: float = 1.0,
) -> tuple[bytes, str, str | None]:
    """The same through the core's streaming entry: stdout, summary, and why the run
    was handed to the reference (``None``: the core took all of it)."""
    from mbmon.core.live import LiveCore, add_counts

    hub, raw, out, summary, view = _wire(as_json, timeout)
    dissector = open_dissector(CaptureConfig(tcp_ports=ports), hub.new_stream)
    live = LiveCore(
        ports=ports,
        timeout=timeout,
        view=view,  # the console's, as sniff gives both the same
        as_json=as_json,
        write=raw.write,
        new_stream=hub.new_stream,
        dissector=dissector,
        pipeline=hub.pipeline,
    )
    hub.add_ticker(live)
    _run(hub, steps, live.packets)
    hub.close()
    out.flush()
    add_counts(summary, live.counts())
    return raw.getvalue(), summary.text(timed=True), live.handed
