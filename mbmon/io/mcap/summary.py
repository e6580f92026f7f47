"""The summary of an mbmon MCAP log (``mbmon info``): one pass over the log.

:func:`summarize` reads every message once and counts what ``info`` reports
(:class:`_Tally`, one method per topic); a damaged message is left out by
:func:`mbmon.io.replay.payload` and reported by the command, damage that
stops the reading is the summary's ``error``.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from mbmon.io.mcap.layout import (
    METADATA_NAME,
    TOPIC_COMMANDS,
    TOPIC_EVENTS,
    TOPIC_FRAMES,
    TOPIC_RAW,
)
from mbmon.io.mcap.reader import LogError, McapLog

__all__ = ["summarize"]

_COUNTED = (TOPIC_RAW, TOPIC_FRAMES, TOPIC_EVENTS, TOPIC_COMMANDS)


class _Tally:
    """What one pass over a log counts (the fields :func:`summarize` returns)."""

    def __init__(self, log: McapLog) -> None:
        self.topics: Counter[str] = Counter({t: 0 for t in log.topics})
        self.first: int | None = None
        self.last: int | None = None
        self.streams: dict[int, dict[str, Any]] = {}
        self.units: Counter[int] = Counter()
        self.fcs: dict[int, Counter[str]] = {}
        self.exceptions: Counter[tuple[int, int]] = Counter()
        self.noise_runs = self.noise_bytes = self.crc_errors = 0
        self.malformed = self.unsolicited = 0
        self.noise_reasons: Counter[str] = Counter()
        self.events: Counter[str] = Counter()
        self.phases: Counter[str] = Counter()
        self.outcomes: list[dict[str, Any]] = []
        self.latencies: list[float] = []
        self.writer_stats: dict[str, Any] | None = None

    def read(self, log: McapLog) -> None:
        """Count every message of ``log`` (raises :class:`LogError` where damage stops it)."""
        from mbmon.io.mcap.layout import frame_chunk
        from mbmon.io.replay import stored_payload

        for msg in log.messages():
            self.topics[msg.topic] += 1
            t = msg.log_time
            self.first = t if self.first is None or t < self.first else self.first
            self.last = t if self.last is None or t > self.last else self.last
            if msg.topic not in _COUNTED:
                continue
            obj = stored_payload(log, msg)  # the fields of a damaged message are not counted
            if obj is None:
                continue
            if msg.topic == TOPIC_RAW:
                self.raw(obj)
            elif msg.topic == TOPIC_FRAMES:
                if "chunk" in obj:  # format 4: the chunk left out, counted as one stored
                    chunk = frame_chunk(obj)  # (payload_problem checked it is whole)
                    if chunk is not None:
                        self.raw(chunk)
                self.frame(obj)
            elif msg.topic == TOPIC_EVENTS:
                self.event(obj)
            else:
                self.command(obj)

    def raw(self, obj: dict[str, Any]) -> None:
        sid = obj.get("stream")
        if sid is not None and sid not in self.streams:
            self.streams[sid] = {
                "id": sid,
                "transport": obj.get("transport"),
                "client": obj.get("client"),
                "server": obj.get("server"),
                "chunks": 0,
                "bytes": 0,
                "frames": 0,
            }
        if obj.get("type") == "chunk" and sid is not None:
            b64 = str(obj.get("data") or "")
            self.streams[sid]["chunks"] += 1
            self.streams[sid]["bytes"] += len(b64) * 3 // 4 - b64.count("=", -2)

    def frame(self, obj: dict[str, Any]) -> None:
        from mbmon.io.replay import FRAME_KINDS

        kind = obj.get("kind")
        if kind == "noise":
            self.noise(obj)
            return
        if kind not in FRAME_KINDS:
            return
        fc = obj.get("fc")
        sid = obj.get("stream")
        if sid is not None:
            self.streams.setdefault(
                sid,
                {"id": sid, "transport": obj.get("transport"), "client": None,
                 "server": None, "chunks": 0, "bytes": 0, "frames": 0},
            )["frames"] += 1  # fmt: skip
        if obj.get("unit") is not None:
            self.units[obj["unit"]] += 1
        if isinstance(fc, int):
            self.fcs.setdefault(fc, Counter())[kind] += 1
            if kind == "exception":
                self.exceptions[(fc, obj.get("exception_code") or 0)] += 1
        if obj.get("crc_ok") is False:
            self.crc_errors += 1
        if obj.get("malformed"):
            self.malformed += 1
        if kind != "request" and obj.get("request_index") is None:
            self.unsolicited += 1
        if obj.get("latency_ms") is not None:
            self.latencies.append(float(obj["latency_ms"]))

    def noise(self, obj: dict[str, Any]) -> None:
        self.noise_runs += 1
        pdu = obj.get("pdu") or ""
        self.noise_bytes += (len(pdu) + 1) // 3
        reason = str(obj.get("malformed") or "")
        self.noise_reasons[reason] += 1
        if "crc" in reason.lower():
            self.crc_errors += 1

    def event(self, obj: dict[str, Any]) -> None:
        if obj.get("kind") != "event":
            return
        if obj.get("index") is None:
            self.writer_stats = obj.get("info")
        else:
            self.events[str(obj.get("event"))] += 1

    def command(self, obj: dict[str, Any]) -> None:
        cmd = obj.get("command") or {}
        phase = str(cmd.get("phase"))
        self.phases[phase] += 1
        if phase in ("success", "fail"):
            self.outcomes.append(
                {
                    "time": obj.get("time"),
                    "unit": obj.get("unit"),
                    "phase": phase,
                    "text": cmd.get("text"),
                    "duration": cmd.get("duration"),
                }
            )

    def traffic(self) -> dict[str, Any]:
        """The figures of the traffic, as :func:`summarize` reports them."""
        from mbmon.format import exception_name, function_name

        first, last, lat = self.first, self.last, self.latencies
        return {
            "start": first / 1e9 if first is not None else None,
            "end": last / 1e9 if last is not None else None,
            "duration": (last - first) / 1e9 if first is not None and last is not None else None,
            "topics": dict(sorted(self.topics.items())),
            "streams": [self.streams[k] for k in sorted(self.streams)],
            "units": {str(k): v for k, v in sorted(self.units.items())},
            "function_codes": {
                f"{fc}": {"name": function_name(fc), **dict(c), "total": sum(c.values())}
                for fc, c in sorted(self.fcs.items())
            },
            "exceptions": [
                {"fc": fc, "code": code, "name": exception_name(code), "count": n}
                for (fc, code), n in sorted(self.exceptions.items())
            ],
            "noise": {
                "runs": self.noise_runs,
                "bytes": self.noise_bytes,
                "reasons": dict(self.noise_reasons),
            },
            "crc_errors": self.crc_errors,
            "malformed": self.malformed,
            "unsolicited": self.unsolicited,
            "latency_ms": (
                {"min": min(lat), "avg": round(sum(lat) / len(lat), 3), "max": max(lat)}
                if lat
                else None
            ),
            "events": dict(sorted(self.events.items())),
            "commands": {"phases": dict(self.phases), "outcomes": self.outcomes},
            "writer_stats": self.writer_stats,
        }


def summarize(log: McapLog) -> dict[str, Any]:
    """Everything ``mbmon info`` reports, as one JSON-able dict (one pass over the log)."""
    from mbmon.io.replay import recorded_options, stored_profile_names

    tally = _Tally(log)
    error: str | None = None
    try:
        tally.read(log)
    except LogError as exc:
        error = str(exc)
    meta = log.metadata.get(METADATA_NAME, {})
    status = log.status
    return {
        "file": str(log.path),
        "size": log.size,
        "finished": status.finished,
        "recovered_messages": status.messages,
        "stopped_at": status.stopped_at,
        "problem": status.problem,
        "error": error,
        "damaged_messages": list(status.skipped.values()),
        "status": status.describe(),
        "recorded_by": meta.get("version"),
        "command_line": recorded_options(log).command_line,
        "source": meta.get("source"),
        "profiles": stored_profile_names(log),
        "profile_attachments": [name for name, _ in log.profiles()],
        "robot": meta.get("robot") or None,
        **tally.traffic(),
    }
