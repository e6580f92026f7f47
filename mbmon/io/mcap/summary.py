"""The summary of an mbmon MCAP log (``mbmon info``): one pass over the log."""

from __future__ import annotations

from collections import Counter
from typing import Any


def summarize(log: Any) -> dict[str, Any]:
    """Everything ``mbmon info`` reports, as one JSON-able dict (one pass over the log)."""
    from mbmon.io.mcap.layout import (
        METADATA_NAME,
        TOPIC_COMMANDS,
        TOPIC_EVENTS,
        TOPIC_FRAMES,
        TOPIC_RAW,
    )
    from mbmon.io.replay import FRAME_KINDS, payload, recorded_options, stored_profile_names

    topics: Counter[str] = Counter({t: 0 for t in log.topics})
    first = last = None
    streams: dict[int, dict[str, Any]] = {}
    units: Counter[int] = Counter()
    fcs: dict[int, Counter[str]] = {}
    exceptions: Counter[tuple[int, int]] = Counter()
    noise_runs = noise_bytes = crc_errors = malformed = unsolicited = 0
    noise_reasons: Counter[str] = Counter()
    events: Counter[str] = Counter()
    phases: Counter[str] = Counter()
    outcomes: list[dict[str, Any]] = []
    latencies: list[float] = []
    writer_stats: dict[str, Any] | None = None
    error: str | None = None
    from mbmon.io.mcap.reader import LogError

    try:
        for msg in log.messages():
            topics[msg.topic] += 1
            t = msg.log_time
            first = t if first is None or t < first else first
            last = t if last is None or t > last else last
            if msg.topic not in (TOPIC_RAW, TOPIC_FRAMES, TOPIC_EVENTS, TOPIC_COMMANDS):
                continue
            obj = payload(log, msg)  # the fields of a damaged message are not counted
            if obj is None:
                continue
            if msg.topic == TOPIC_RAW:
                sid = obj.get("stream")
                if sid is not None and sid not in streams:
                    streams[sid] = {
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
                    streams[sid]["chunks"] += 1
                    streams[sid]["bytes"] += len(b64) * 3 // 4 - b64.count("=", -2)
                continue
            kind = obj.get("kind")
            if msg.topic == TOPIC_FRAMES and kind in FRAME_KINDS:
                fc = obj.get("fc")
                sid = obj.get("stream")
                if sid is not None:
                    streams.setdefault(
                        sid,
                        {"id": sid, "transport": obj.get("transport"), "client": None,
                         "server": None, "chunks": 0, "bytes": 0, "frames": 0},
                    )["frames"] += 1  # fmt: skip
                if obj.get("unit") is not None:
                    units[obj["unit"]] += 1
                if isinstance(fc, int):
                    fcs.setdefault(fc, Counter())[kind] += 1
                if kind == "exception" and isinstance(fc, int):
                    exceptions[(fc, obj.get("exception_code") or 0)] += 1
                if obj.get("crc_ok") is False:
                    crc_errors += 1
                if obj.get("malformed"):
                    malformed += 1
                if kind != "request" and obj.get("request_index") is None:
                    unsolicited += 1
                if obj.get("latency_ms") is not None:
                    latencies.append(float(obj["latency_ms"]))
            elif msg.topic == TOPIC_FRAMES and kind == "noise":
                noise_runs += 1
                pdu = obj.get("pdu") or ""
                noise_bytes += (len(pdu) + 1) // 3
                reason = str(obj.get("malformed") or "")
                noise_reasons[reason] += 1
                if "crc" in reason.lower():
                    crc_errors += 1
            elif msg.topic == TOPIC_EVENTS and kind == "event":
                if obj.get("index") is None:
                    writer_stats = obj.get("info")
                else:
                    events[str(obj.get("event"))] += 1
            elif msg.topic == TOPIC_COMMANDS:
                cmd = obj.get("command") or {}
                phase = str(cmd.get("phase"))
                phases[phase] += 1
                if phase in ("success", "fail"):
                    outcomes.append(
                        {
                            "time": obj.get("time"),
                            "unit": obj.get("unit"),
                            "phase": phase,
                            "text": cmd.get("text"),
                            "duration": cmd.get("duration"),
                        }
                    )
    except LogError as exc:
        error = str(exc)
    meta = log.metadata.get(METADATA_NAME, {})
    command_line = recorded_options(log).command_line
    status = log.status
    from mbmon.format import exception_name, function_name

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
        "command_line": command_line,
        "source": meta.get("source"),
        "profiles": stored_profile_names(log),
        "profile_attachments": [name for name, _ in log.profiles()],
        "robot": meta.get("robot") or None,
        "start": first / 1e9 if first is not None else None,
        "end": last / 1e9 if last is not None else None,
        "duration": (last - first) / 1e9 if first is not None and last is not None else None,
        "topics": dict(sorted(topics.items())),
        "streams": [streams[k] for k in sorted(streams)],
        "units": {str(k): v for k, v in sorted(units.items())},
        "function_codes": {
            f"{fc}": {"name": function_name(fc), **dict(c), "total": sum(c.values())}
            for fc, c in sorted(fcs.items())
        },
        "exceptions": [
            {"fc": fc, "code": code, "name": exception_name(code), "count": n}
            for (fc, code), n in sorted(exceptions.items())
        ],
        "noise": {"runs": noise_runs, "bytes": noise_bytes, "reasons": dict(noise_reasons)},
        "crc_errors": crc_errors,
        "malformed": malformed,
        "unsolicited": unsolicited,
        "latency_ms": (
            {
                "min": min(latencies),
                "avg": round(sum(latencies) / len(latencies), 3),
                "max": max(latencies),
            }
            if latencies
            else None
        ),
        "events": dict(sorted(events.items())),
        "commands": {"phases": dict(phases), "outcomes": outcomes},
        "writer_stats": writer_stats,
    }
