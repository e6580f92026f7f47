"""``mbmon info``: the summary of an MCAP log, as text or JSON."""

from __future__ import annotations

import argparse
import json
import sys
from typing import IO, Any

from mbmon.commands.common import EXIT_BAD_INPUT, EXIT_OK
from mbmon.commands.logfile import err, open_log, progress, report_skipped
from mbmon.timefmt import add_time_option

EPILOG = """\
examples:
  mbmon info cell.mcap          time span, messages per topic, streams, units, function
                                codes, exceptions, noise/CRC errors, robot commands
  mbmon info cell.mcap --json   the same as one JSON object
"""


def register(sub: Any) -> None:
    """Add ``info`` to the CLI's sub-parsers."""
    fmt = argparse.RawDescriptionHelpFormatter

    info = sub.add_parser(
        "info",
        help="summarise an MCAP log: span, topics, streams, function codes, errors, commands",
        description="Summarise an MCAP log written by mbmon. An unfinished log (the "
        "recording was killed) is read as far as it goes; info says how much was recovered.",
        epilog=EPILOG,
        formatter_class=fmt,
    )
    info.add_argument("log", metavar="LOG.mcap", help="an MCAP log written by mbmon")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    add_time_option(info, since_until=False)
    info.set_defaults(func=run_info)


def _print_info(s: dict[str, Any], out: IO[str], mode: str = "a") -> None:
    """The summary as text; times in the ``-t`` mode ``mode`` (the span with its date)."""
    from mbmon.timefmt import TimeFormat, human_span

    fmt = TimeFormat.for_span(mode, s["start"], s["end"])
    dated = TimeFormat({"a": "ad", "u": "ud"}.get(mode, mode), origin=s["start"])

    def _when(ts: float | None, fmt: TimeFormat = fmt) -> str:
        return "-" if ts is None else fmt.text(ts)

    w = out.write
    w(f"file:        {s['file']} ({s['size']} bytes)\n")
    w(f"state:       {s['status']}\n")
    if s["error"]:
        w(f"damage:      {s['error']}\n")
    if s["damaged_messages"]:
        w(f"damaged:     {len(s['damaged_messages'])} messages left out (see stderr)\n")
    if s["recorded_by"]:
        w(f"recorded by: mbmon {s['recorded_by']}: {' '.join(s['command_line'])}\n")
    if s["source"]:
        w(f"source:      {s['source']}\n")
    w(f"profiles:    {', '.join(s['profiles']) or '-'}")
    if s["profile_attachments"]:
        w(f" (attached: {', '.join(s['profile_attachments'])})")
    w("\n")
    if s["robot"]:
        w(f"robot:       {s['robot']}\n")
    dur = f" ({human_span(s['duration'])})" if s["duration"] is not None else ""
    w(f"time span:   {_when(s['start'], dated)} .. {_when(s['end'], dated)}{dur}\n")
    w("messages per topic:\n")
    for topic, n in s["topics"].items():
        w(f"  {topic:<18} {n}\n")
    w(f"streams: {len(s['streams'])}\n")
    for st in s["streams"][:50]:
        peers = (
            st["client"] if st["client"] == st["server"] else f"{st['client']} <> {st['server']}"
        )
        w(
            f"  #{st['id']} {st['transport']} {peers}: {st['frames']} frames, "
            f"{st['chunks']} chunks, {st['bytes']} bytes\n"
        )
    if len(s["streams"]) > 50:
        w(f"  ... {len(s['streams']) - 50} more\n")
    units = ", ".join(f"{u} ({n} frames)" for u, n in s["units"].items())
    w(f"units:       {units or '-'}\n")
    w("function codes:\n" if s["function_codes"] else "function codes: -\n")
    for fc, c in s["function_codes"].items():
        parts = [f"{k}s {c[k]}" for k in ("request", "response", "exception") if c.get(k)]
        w(f"  {int(fc):02X} {c['name']}: {c['total']} ({', '.join(parts)})\n")
    if s["exceptions"]:
        w("exceptions:\n")
        for e in s["exceptions"]:
            w(f"  fc {e['fc']:02X}: {e['code']:02X} {e['name']}: {e['count']}\n")
    else:
        w("exceptions:  none\n")
    nz = s["noise"]
    reasons = "; ".join(f"{r or '?'}: {n}" for r, n in nz["reasons"].items())
    reasons = f" ({reasons})" if reasons else ""
    w(f"noise:       {nz['runs']} runs, {nz['bytes']} bytes{reasons}\n")
    w(f"CRC errors:  {s['crc_errors']}\n")
    w(f"malformed:   {s['malformed']}   unsolicited responses: {s['unsolicited']}\n")
    if s["latency_ms"]:
        lat = s["latency_ms"]
        w(f"latency:     min {lat['min']} ms, avg {lat['avg']} ms, max {lat['max']} ms\n")
    ev = ", ".join(f"{k} {v}" for k, v in s["events"].items())
    w(f"events:      {ev or 'none'}\n")
    cmds = s["commands"]
    if cmds["phases"]:
        ph = ", ".join(f"{k} {v}" for k, v in cmds["phases"].items())
        w(f"commands:    {ph}\n")
        for o in cmds["outcomes"][:30]:
            dur = f" after {o['duration']:.3f} s" if o["duration"] is not None else ""
            w(f"  {_when(o['time'])} unit {o['unit']}: {o['phase']}{dur}: {o['text']}\n")
        if len(cmds["outcomes"]) > 30:
            w(f"  ... {len(cmds['outcomes']) - 30} more outcomes\n")
    else:
        w("commands:    none\n")


def run_info(args: argparse.Namespace) -> int:
    """``mbmon info``: the summary of a log (text or --json)."""
    from mbmon.io.mcap.summary import summarize

    log, status = open_log(args.log, "info")
    if log is None:
        return status
    bar = progress(log)
    with log:
        try:
            summary = summarize(log)
        finally:
            bar.close()
    if args.json:
        from mbmon.format import finite

        print(json.dumps(finite(summary), ensure_ascii=False, indent=2, default=str))
    else:
        _print_info(summary, sys.stdout, args.time_format)
    if summary["error"]:
        err(summary["error"])
    report_skipped(log)
    return EXIT_BAD_INPUT if summary["error"] or summary["damaged_messages"] else EXIT_OK
