"""``mbmon report``: the figures of a run, as terminal tables or as pictures.

This module owns what a report says about a run, computed from its records'
``read --json`` objects (a capture decoded through the one flow, or a log's
stored records: the same objects, so the same report):

* **poll cycles** per client and register block (client, server, unit,
  function code, address, count): requests, period (median interval), jitter
  (standard deviation of the intervals), missed cycles (an interval of ``k``
  periods, ``k >= 1.5``, counts ``round(k) - 1``), latency percentiles
  (p50/p95/p99/max), exceptions and timeouts;
* **latency** of every answer (percentiles and a histogram);
* **faults on a timeline**: every exception and unanswered request;
* **commands** (with a device profile): each command's phases and outcome;
* **RTU bus health** per bus stream: frames, CRC errors, silence gaps between
  frames (from one frame's time to the next one's, less the next frame's own
  time on the wire when the baud rate is known: a histogram) and the time the
  bus was busy (utilisation, 11 bits a byte, with the baud rate).

:func:`analyse` computes the figures (pure, no plotting); :func:`text_tables`
renders them for the terminal; :func:`render_png` draws the pictures with
matplotlib on its Agg backend (imported only there: the ``report`` extra) and
:func:`render_html` makes one self-contained HTML page with the PNGs embedded,
which opens offline.
"""

from __future__ import annotations

import base64
import html
import math
import statistics
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any

__all__ = [
    "Block",
    "Figures",
    "MissingExtra",
    "analyse",
    "percentile",
    "render_html",
    "render_png",
    "text_tables",
]

FRAME_KINDS = ("request", "response", "exception")


class MissingExtra(Exception):
    """A plotting library the report needs is not installed (the message names
    the pip command)."""


def percentile(values: list[float], q: float) -> float:
    """The ``q``-th percentile (0..100) of ``values`` by linear interpolation
    between the closest ranks (numpy's default), ``nan`` for no values."""
    if not values:
        return math.nan
    data = sorted(values)
    pos = (len(data) - 1) * q / 100.0
    low = math.floor(pos)
    high = min(low + 1, len(data) - 1)
    return data[low] + (data[high] - data[low]) * (pos - low)


@dataclass(slots=True)
class Block:
    """One polled register block of one client (see the module docstring)."""

    client: str
    server: str
    unit: int | None
    fc: int | None
    address: int | None
    count: int | None
    times: list[float] = field(default_factory=list)  # request times
    latencies_ms: list[float] = field(default_factory=list)
    exceptions: int = 0
    timeouts: int = 0

    @property
    def label(self) -> str:
        what = f"fc {self.fc}" if self.fc is not None else "fc ?"
        if self.address is not None:
            end = self.address + max((self.count or 1) - 1, 0)
            what += f" {self.address}" + (f"..{end}" if end != self.address else "")
        return f"{self.client} → {self.server} u{self.unit} {what}"

    @property
    def intervals(self) -> list[float]:
        times = self.times
        return [b - a for a, b in pairwise(times)]

    @property
    def period(self) -> float | None:
        """Median interval between requests (s), with two requests or more."""
        intervals = self.intervals
        return statistics.median(intervals) if intervals else None

    @property
    def jitter(self) -> float | None:
        """Standard deviation of the intervals (s), with three requests or more."""
        intervals = self.intervals
        return statistics.pstdev(intervals) if len(intervals) >= 2 else None

    @property
    def missed(self) -> int:
        """Cycles missed: an interval of ``k`` periods (``k >= 1.5``) misses
        ``round(k) - 1``."""
        period = self.period
        if not period:
            return 0
        return sum(round(i / period) - 1 for i in self.intervals if i >= 1.5 * period)


@dataclass(slots=True)
class Bus:
    """An RTU bus (or RTU-over-TCP stream): frames, CRC errors, silence gaps."""

    name: str
    frames: int = 0
    crc_errors: int = 0
    bytes: int = 0
    gaps_ms: list[float] = field(default_factory=list)
    first: float | None = None
    last: float | None = None


@dataclass(slots=True)
class Figures:
    """What :func:`analyse` found in a run."""

    source: str = ""
    first: float | None = None
    last: float | None = None
    records: int = 0
    blocks: list[Block] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    #: (time, kind, line); no time for a record without one (an RTU dump's, a damaged log's)
    faults: list[tuple[float | None, str, str]] = field(default_factory=list)
    # (time written, command text, outcome: its last phase, with the duration when known)
    commands: list[tuple[float | None, str, str]] = field(default_factory=list)
    buses: list[Bus] = field(default_factory=list)
    baud: int | None = None

    @property
    def exceptions(self) -> int:
        return sum(1 for _, kind, _ in self.faults if kind == "exception")

    @property
    def timeouts(self) -> int:
        return sum(1 for _, kind, _ in self.faults if kind == "timeout")


def analyse(
    objs: Iterable[Mapping[str, Any]], *, source: str = "", baud: int | None = None
) -> Figures:
    """The figures of a run from its records' ``read --json`` objects, in order."""
    fig = Figures(source=source, baud=baud)
    blocks: dict[tuple[Any, ...], Block] = {}
    by_index: dict[int, Block] = {}  # request record index -> its block
    buses: dict[Any, Bus] = {}
    last_frame_end: dict[Any, float] = {}
    commands: dict[Any, int] = {}  # (stream, unit) -> its latest command in fig.commands
    for obj in objs:
        fig.records += 1
        when = obj.get("time")  # a damaged log may hold anything here
        ts = when if isinstance(when, int | float) else None
        if ts is not None:
            fig.first = ts if fig.first is None else min(fig.first, ts)
            fig.last = ts if fig.last is None else max(fig.last, ts)
        kind = obj.get("kind")
        if kind in FRAME_KINDS:
            request = kind == "request"
            client, server = (obj.get("src"), obj.get("dst"))
            if not request:
                client, server = server, client
            key = (
                client,
                server,
                obj.get("unit"),
                obj.get("fc"),
                obj.get("address"),
                obj.get("count"),
            )
            block = blocks.get(key)
            if block is None:
                block = blocks[key] = Block(str(client), str(server), *key[2:])
            if request:
                if ts is not None:
                    block.times.append(ts)
                index = obj.get("index")
                if isinstance(index, int):
                    by_index[index] = block
            else:
                latency = obj.get("latency_ms")
                if isinstance(latency, int | float):
                    block.latencies_ms.append(float(latency))
                    fig.latencies_ms.append(float(latency))
                if kind == "exception":
                    block.exceptions += 1
                    fig.faults.append((ts, "exception", str(obj.get("line") or "")))
        elif kind == "event" and obj.get("event") == "timeout":
            info = obj.get("info")
            index = info.get("request_index") if isinstance(info, Mapping) else None
            block = by_index.get(index) if isinstance(index, int) else None
            if block is not None:
                block.timeouts += 1
            fig.faults.append((ts, "timeout", str(obj.get("line") or "")))
        elif kind == "command":
            _command(fig, obj, ts, commands)
        transport = obj.get("transport")
        if isinstance(transport, str) and transport.startswith("rtu") and kind in (
            *FRAME_KINDS, "noise",
        ):  # fmt: skip
            _bus_record(obj, kind, transport, ts, baud, buses, last_frame_end)
    fig.blocks = sorted(
        blocks.values(), key=lambda b: (b.client, b.server, str(b.unit), str(b.fc), str(b.address))
    )
    fig.blocks = [b for b in fig.blocks if b.times or b.latencies_ms or b.exceptions]
    fig.buses = list(buses.values())
    return fig


def _command(fig: Figures, obj: Mapping[str, Any], ts: Any, commands: dict[Any, int]) -> None:
    """A robot command's record: a new row of ``fig.commands``, or the outcome of the
    latest row of its (stream, unit) (``commands`` holds where that row is)."""
    command = obj.get("command")
    if not isinstance(command, Mapping):
        return
    text = str(command.get("text") or "")
    phase = str(command.get("phase") or "")
    duration = command.get("duration")
    outcome = phase + (f" after {duration:.3f} s" if isinstance(duration, int | float) else "")
    key = (obj.get("stream"), obj.get("unit"))
    at = commands.get(key)
    if at is None or phase == "written" or fig.commands[at][1] != text:
        commands[key] = len(fig.commands)
        fig.commands.append((ts, text, outcome))
    else:
        fig.commands[at] = (fig.commands[at][0], text, outcome)


def _bus_record(
    obj: Mapping[str, Any],
    kind: Any,
    transport: str,
    ts: float | None,
    baud: int | None,
    buses: dict[Any, Bus],
    last_frame_end: dict[Any, float],
) -> None:
    """An RTU frame's or noise's record on its bus: bytes, frames, CRC errors and the
    silence before it (``last_frame_end``: per stream, when its last frame ended)."""
    server = obj.get("dst") if kind == "request" else obj.get("src")
    name = str(server) if transport == "rtu" else f"{server} (RTU over TCP/UDP)"
    bus = buses.get(obj.get("stream"))
    if bus is None:
        bus = buses[obj.get("stream")] = Bus(str(name))
    pdu = obj.get("pdu")
    # a frame's pdu lacks its unit id and CRC; noise's holds every byte it had
    size = len(str(pdu).split()) + (0 if kind == "noise" else 3) if pdu else 0
    bus.bytes += size
    if kind == "noise":
        if "CRC" in " ".join(obj.get("notes") or ()):
            bus.crc_errors += 1
    else:
        bus.frames += 1
    if ts is not None:
        previous = last_frame_end.get(obj.get("stream"))
        on_wire = size * 11 / baud if baud else 0.0  # this frame's own bytes
        if previous is not None and ts - on_wire >= previous:
            bus.gaps_ms.append((ts - on_wire - previous) * 1000.0)
        last_frame_end[obj.get("stream")] = ts
        bus.first = ts if bus.first is None else bus.first
        bus.last = ts


# --------------------------------------------------------------------------- terminal


def _ms(seconds: float | None) -> str:
    return "-" if seconds is None or math.isnan(seconds) else f"{seconds * 1000:.1f}"


def _num(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.1f}"


def _table(headers: list[str], rows: list[list[str]]) -> list[str]:
    widths = [
        max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(headers)
    ]
    out = ["  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True)).rstrip()]
    out.append("  ".join("-" * w for w in widths))
    out += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    return out


def histogram(values: list[float], bins: int = 10) -> list[tuple[float, float, int]]:
    """``bins`` equal bins over ``values``: ``(low, high, count)``."""
    if not values:
        return []
    lo, hi = min(values), max(values)
    if hi == lo:
        return [(lo, hi, len(values))]
    width = (hi - lo) / bins
    counts = [0] * bins
    for v in values:
        counts[min(int((v - lo) / width), bins - 1)] += 1
    return [(lo + i * width, lo + (i + 1) * width, n) for i, n in enumerate(counts)]


def text_tables(fig: Figures) -> str:
    """The report as tables for a terminal (the same figures as the pictures)."""
    lines = [f"report of {fig.source}: {fig.records} records"]
    if fig.first is not None and fig.last is not None:
        from mbmon.timefmt import human_span

        lines[0] += f" over {human_span(fig.last - fig.first)}"
    lines += ["", "poll cycles per client and register block"]
    rows = []
    for b in fig.blocks:
        lat = b.latencies_ms
        rows.append([
            b.label, str(len(b.times)), _ms(b.period), _ms(b.jitter), str(b.missed),
            _num(percentile(lat, 50)), _num(percentile(lat, 95)), _num(percentile(lat, 99)),
            _num(max(lat) if lat else math.nan), str(b.exceptions), str(b.timeouts),
        ])  # fmt: skip
    lines += _table(
        ["block", "requests", "period ms", "jitter ms", "missed", "p50 ms", "p95 ms", "p99 ms",
         "max ms", "exceptions", "timeouts"],
        rows,
    )  # fmt: skip
    lat = fig.latencies_ms
    lines += ["", f"latency of {len(lat)} answers (ms)"]
    lines += _table(
        ["p50", "p90", "p95", "p99", "max"],
        [
            [_num(percentile(lat, q)) for q in (50, 90, 95, 99)]
            + [_num(max(lat) if lat else math.nan)]
        ],
    )
    if lat:
        lines += ["", "latency histogram (ms)"]
        top = max(n for _, _, n in histogram(lat))
        for lo, hi, n in histogram(lat):
            lines.append(f"  {lo:8.2f} .. {hi:8.2f}  {n:7d}  {'#' * round(40 * n / top)}")
    lines += ["", f"faults: {fig.exceptions} exceptions, {fig.timeouts} timeouts"]
    for _ts, kind, line in fig.faults[:50]:
        lines.append(f"  {kind:9s}  {line}")
    if len(fig.faults) > 50:
        lines.append(f"  ... and {len(fig.faults) - 50} more")
    if fig.commands:
        lines += ["", "commands and outcomes"]
        lines += _table(["command", "outcome"], [[text, phase] for _, text, phase in fig.commands])
    if fig.buses:
        lines += ["", "RTU bus health"]
        rows = []
        for bus in fig.buses:
            util = utilisation(bus, fig.baud)
            gaps = bus.gaps_ms
            rows.append([
                bus.name, str(bus.frames), str(bus.crc_errors), _num(percentile(gaps, 50)),
                _num(min(gaps) if gaps else math.nan), "-" if util is None else f"{util:.1%}",
            ])  # fmt: skip
        lines += _table(
            ["bus", "frames", "CRC errors", "gap p50 ms", "gap min ms", "utilisation"], rows
        )
    return "\n".join(lines)


def utilisation(bus: Bus, baud: int | None) -> float | None:
    """The share of the bus's time its frames took (11 bits a byte), with a baud rate."""
    if not baud or bus.first is None or bus.last is None or bus.last <= bus.first:
        return None
    return bus.bytes * 11 / baud / (bus.last - bus.first)


# --------------------------------------------------------------------------- pictures


def _pyplot() -> Any:
    try:
        import matplotlib
    except ImportError:
        raise MissingExtra(
            "the report's pictures need matplotlib: pip install 'mbmon[report]'"
        ) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def render_png(fig: Figures) -> list[tuple[str, str, bytes]]:
    """Every picture of the report: ``(name, title, PNG bytes)``."""
    import io

    plt = _pyplot()
    out: list[tuple[str, str, bytes]] = []

    def save(name: str, title: str, figure: Any) -> None:
        buf = io.BytesIO()
        figure.tight_layout()
        figure.savefig(buf, format="png", dpi=100)
        plt.close(figure)
        out.append((name, title, buf.getvalue()))

    blocks = [b for b in fig.blocks if b.period]
    if blocks:
        figure, ax = plt.subplots(figsize=(9, 1 + 0.45 * len(blocks)))
        periods = [b.period * 1000 for b in blocks]  # type: ignore[operator]
        jitters = [(b.jitter or 0.0) * 1000 for b in blocks]
        ax.barh(range(len(blocks)), periods, xerr=jitters, color="#4878a8", capsize=3)
        ax.set_yticks(range(len(blocks)), [b.label for b in blocks], fontsize=7)
        for i, b in enumerate(blocks):
            if b.missed:
                ax.annotate(f" {b.missed} missed", (periods[i], i), fontsize=7, color="#b03030")
        ax.set_xlabel("poll period (ms), bar: median, whisker: jitter (standard deviation)")
        save("poll_cycles", "Poll cycle per client and register block", figure)
    if fig.latencies_ms:
        figure, ax = plt.subplots(figsize=(9, 3.5))
        ax.hist(fig.latencies_ms, bins=40, color="#4878a8")
        for q, style in ((50, "-"), (95, "--"), (99, ":")):
            value = percentile(fig.latencies_ms, q)
            ax.axvline(value, color="#b03030", linestyle=style, label=f"p{q} {value:.1f} ms")
        ax.set_xlabel("latency (ms)")
        ax.set_ylabel("answers")
        ax.legend()
        save("latency", "Latency histogram and percentiles", figure)
    if fig.first is not None and fig.last is not None:
        figure, ax = plt.subplots(figsize=(9, 2.2))
        for kind, color, y in (("exception", "#d08020", 1), ("timeout", "#b03030", 0)):
            times = [ts - fig.first for ts, k, _ in fig.faults if k == kind and ts is not None]
            ax.scatter(
                times,
                [y] * len(times),
                marker="|",
                s=300,
                color=color,
                label=f"{kind} ({len(times)})",
            )
        ax.set_yticks([0, 1], ["timeouts", "exceptions"])
        ax.set_xlim(0, max(fig.last - fig.first, 1e-3))
        ax.set_ylim(-0.7, 1.7)
        ax.set_xlabel("seconds from the start of the run")
        save("faults", "Exceptions and timeouts on a timeline", figure)
    if fig.commands:
        counts: dict[str, int] = defaultdict(int)
        for _, _, outcome in fig.commands:
            counts[outcome.split(" after ")[0]] += 1
        figure, ax = plt.subplots(figsize=(6, 2.5))
        ax.bar(list(counts), list(counts.values()), color="#4878a8")
        ax.set_ylabel("commands")
        save("commands", "Commands by outcome", figure)
    for n, bus in enumerate(fig.buses):
        if not bus.gaps_ms:
            continue
        figure, ax = plt.subplots(figsize=(9, 3))
        ax.hist(bus.gaps_ms, bins=40, color="#4878a8")
        ax.set_xlabel("silence between frames (ms)")
        ax.set_ylabel("gaps")
        util = utilisation(bus, fig.baud)
        extra = f", utilisation {util:.1%}" if util is not None else ""
        save(
            f"bus{n + 1}", f"RTU bus {bus.name}: gaps ({bus.crc_errors} CRC errors{extra})", figure
        )
    return out


def render_html(fig: Figures, pictures: list[tuple[str, str, bytes]]) -> str:
    """One self-contained page: the tables and every picture, embedded as PNG."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>mbmon report: {html.escape(fig.source)}</title>",
        "<style>body{font-family:sans-serif;margin:2em;max-width:1100px}"
        "pre{background:#f4f4f4;padding:1em;overflow-x:auto;font-size:12px}"
        "figure{margin:1.5em 0}img{max-width:100%}</style></head><body>",
        f"<h1>mbmon report: {html.escape(fig.source)}</h1>",
    ]
    for name, title, png in pictures:
        data = base64.b64encode(png).decode("ascii")
        parts.append(
            f'<figure id="{name}"><figcaption><h2>{html.escape(title)}</h2></figcaption>'
            f'<img alt="{html.escape(title)}" src="data:image/png;base64,{data}"></figure>'
        )
    parts.append("<h2>Figures</h2><pre>" + html.escape(text_tables(fig)) + "</pre>")
    parts.append("</body></html>")
    return "\n".join(parts)
