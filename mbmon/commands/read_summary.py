"""What ``mbmon read`` says on stderr after a read: the summary, the ports found by
their structure, and the hints when no Modbus was found or ``--robot`` never appeared."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from mbmon.commands.common import err


def report(
    summary: Any, capture_stats: dict[str, Any], args: argparse.Namespace, *, timed: bool
) -> None:
    """The summary and the hints a user needs after a read, on stderr."""
    try:
        print(summary.text(timed=timed), file=sys.stderr, flush=True)
    except (OSError, ValueError):
        return
    for line in detected_lines(capture_stats.get("detected") or []):
        err(line)
    if summary.frames == 0 and not args.rtu_raw:
        busiest = capture_stats.get("busiest_ports") or []
        ports = ", ".join(f"{proto}/{p} ({n} packets)" for proto, p, n in busiest[:5])
        asked = ", ".join(str(p) for p in sorted({502, *args.port, *args.rtu_port}))
        hint = f"no Modbus found on port {asked}"
        if not args.no_detect:
            hint += " nor by its structure on any other TCP port"
        if ports:
            first = busiest[0][1]
            hint += f"; busiest ports: {ports}; try --port {first} (or --rtu-port {first})"
        err(hint)
    if args.robot and summary.streams and not summary.robot_seen:
        err(f"warning: the robot {args.robot} (--robot) appears in no stream of this capture")


def capture_stats(sources: list[Any]) -> dict[str, Any]:
    """The capture readers' figures of ``read``'s inputs as one (what :func:`report`
    asks): the ports found by their structure, and the busiest other ports."""
    found: list[Any] = []
    ports: dict[tuple[str, int], int] = {}
    for source in sources:
        stats = getattr(source, "capture_stats", None) or {}
        found.extend(stats.get("detected") or [])
        for proto, port, packets in stats.get("busiest_ports") or []:
            ports[(proto, port)] = ports.get((proto, port), 0) + packets
    busiest = sorted(((p, n, c) for (p, n), c in ports.items()), key=lambda x: -x[2])
    return {"detected": found, "busiest_ports": busiest}


def detected_lines(found: list[tuple[str, int, str, int]]) -> list[str]:
    """One line per port that port detection found (the dissector's
    ``detected()``): the transport, the port, its servers and connections."""
    ports: dict[tuple[str, int], list[tuple[str, int]]] = {}
    for transport, number, server, streams in found:
        ports.setdefault((transport, number), []).append((server, streams))
    lines = []
    for (transport, number), servers in ports.items():
        what = "RTU over TCP" if transport == "rtu-over-tcp" else "Modbus/TCP"
        names = ", ".join(server for server, _ in servers[:3])
        if len(servers) > 3:
            names += f" and {len(servers) - 3} more"
        streams = sum(n for _, n in servers)
        lines.append(
            f"found {what} on port {number} by its structure: {streams} connection"
            f"{'s' if streams != 1 else ''} to {names} (--no-detect turns this off)"
        )
    return lines
