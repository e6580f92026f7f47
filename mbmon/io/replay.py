"""Reading records back out of an mbmon MCAP log: stored, filtered, re-decoded, paced.

This module owns the meaning of a log for the log commands (``replay``,
``info``, ``export``):

- :func:`logged_records` merges the ``read --json`` objects stored on
  ``/modbus/frames``, ``/mbmon/events`` and ``/hrss/commands`` with the
  monitor lines of ``/modbus/monitor`` into one :class:`LoggedRecord` per
  record, in record order (a noise run is stored on two topics and comes out
  once);
- :func:`raw_items` rebuilds the chunks and source events of ``/modbus/raw``
  so the current decoder can run again (``--redecode``);
- :func:`recorded_options` recovers the options of the recording command
  (profiles, timeout, baud, robot) from the log's metadata (older logs: from
  their stored command line) and attachments;
- :class:`RecordFilter` and :func:`parse_when` implement the filters, and
  :class:`Pacer` the ``--speed`` schedule (one monotonic start, no drift).
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import datetime as _dt
import io
import json
import re
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mbmon.io.mcap_reader import LogError, McapLog
from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.sinks.mcap import (
    METADATA_NAME,
    RECORD_TOPICS,
    TOPIC_MONITOR,
    TOPIC_RAW,
)

FRAME_KINDS = frozenset({"request", "response", "exception"})


@dataclass(slots=True)
class LoggedRecord:
    """One record as stored: its ``read --json`` object and its monitor line.

    ``obj`` is ``None`` (or ``line`` is) only for a record cut in half by a
    crash at the very end of an unfinished log.
    """

    index: int
    time: float
    obj: dict[str, Any] | None = None
    line: str | None = None
    level: int | None = None

    @property
    def text(self) -> str:
        """The monitor line as shown live."""
        if self.line is not None:
            return self.line
        if self.obj is not None:
            return str(self.obj.get("line") or "")
        return ""


def logged_records(log: McapLog) -> Iterator[LoggedRecord]:
    """Every record of the log in record order (see the module docstring)."""
    current: LoggedRecord | None = None
    for msg in log.messages((*RECORD_TOPICS, TOPIC_MONITOR)):
        data = msg.json()
        if not isinstance(data, dict):
            continue
        if msg.topic == TOPIC_MONITOR:
            index = data.get("line")
            if not isinstance(index, int):
                continue
            if current is not None and current.index == index:
                current.line = data.get("message")
                current.level = data.get("level")
                continue
            if current is not None:
                yield current
            ts = msg.log_time / 1e9
            current = LoggedRecord(index, ts, None, data.get("message"), data.get("level"))
            continue
        index = data.get("index")
        if not isinstance(index, int):
            continue  # the writer's own stats events
        if current is not None and current.index == index:
            if current.obj is None:
                current.obj = data
            continue
        if current is not None:
            yield current
        current = LoggedRecord(index, float(data.get("time") or msg.log_time / 1e9), data)
    if current is not None:
        yield current


def writer_stats(log: McapLog) -> dict[str, Any] | None:
    """The last stats event the log writer stored (counters at the end of the log)."""
    last = None
    for msg in log.messages(["/mbmon/events"]):
        data = msg.json()
        if isinstance(data, dict) and data.get("index") is None and data.get("event") == "stats":
            last = data.get("info")
    return last


def raw_items(log: McapLog) -> Iterator[Chunk | Event]:
    """The chunks and source events of ``/modbus/raw``, in capture order."""
    streams: dict[int, Stream] = {}
    for msg in log.messages([TOPIC_RAW]):
        data = msg.json()
        try:
            sid = data.get("stream")
            stream: Stream | None = None
            if sid is not None:
                stream = streams.get(sid)
                if stream is None:
                    stream = Stream(
                        sid, Transport(data["transport"]), data["client"], data["server"]
                    )
                    streams[sid] = stream
            ts = float(data["ts"])
            if data.get("type") == "event":
                yield Event(ts, stream, EventKind(data["event"]), dict(data.get("info") or {}))
            else:
                if stream is None:
                    raise ValueError("chunk without a stream")
                yield Chunk(
                    ts, stream, Direction(data["direction"]), base64.b64decode(data["data"])
                )
        except (KeyError, ValueError, TypeError, AttributeError) as exc:
            raise LogError(f"{log.path}: damaged /modbus/raw message: {exc}") from None


# --------------------------------------------------------------------------- recorded options


@dataclass(slots=True)
class RecordedOptions:
    """What the recording command was told: enough to decode the raw bytes the same way."""

    command_line: list[str] = field(default_factory=list)
    profile_specs: list[str] = field(default_factory=list)
    timeout: float = 1.0
    baud: int | None = None
    robot: str | None = None
    robot_is_client: bool = False


def recorded_options(log: McapLog) -> RecordedOptions:
    """Options of the recording command, from the metadata record ``mbmon``.

    The analysis settings come from the keys ``profile_specs``, ``timeout`` and
    ``baud``, which the writer stores from what the recording was given. A log
    written before those keys existed (or with one of them damaged) has them
    recovered by parsing its stored ``command_line`` with today's parser.
    """
    meta = log.metadata.get(METADATA_NAME, {})
    opts = RecordedOptions()
    try:
        line = json.loads(meta.get("command_line", "[]"))
        if isinstance(line, list):
            opts.command_line = [str(x) for x in line]
    except ValueError:
        pass
    opts.robot = meta.get("robot") or None
    opts.robot_is_client = meta.get("robot_is_client") == "true"
    specs = _stored(meta, "profile_specs", _is_spec_list)
    timeout = _stored(meta, "timeout", _is_timeout)
    baud = _stored(meta, "baud", _is_baud)
    if _MISSING in (specs, timeout, baud) and len(opts.command_line) > 1:
        parsed = _reparse(opts.command_line[1:])  # an older log: the command line says
        if parsed is not None:
            if specs is _MISSING:
                specs = list(getattr(parsed, "profile", None) or [])
            if timeout is _MISSING:
                timeout = float(getattr(parsed, "timeout", None) or 1.0)
            if baud is _MISSING:
                baud = getattr(parsed, "baud", None)
    if specs is not _MISSING:
        opts.profile_specs = [str(spec) for spec in specs]
    if timeout is not _MISSING:
        opts.timeout = float(timeout)
    if baud is not _MISSING:
        opts.baud = baud
    return opts


_MISSING: Any = object()


def _stored(meta: Mapping[str, str], key: str, valid: Callable[[Any], bool]) -> Any:
    """The JSON value a metadata key holds, or ``_MISSING`` when it is absent or not valid."""
    text = meta.get(key)
    if text is None:
        return _MISSING
    try:
        value = json.loads(text)
    except ValueError:
        return _MISSING
    return value if valid(value) else _MISSING


def _is_spec_list(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(spec, str) for spec in value)


def _is_timeout(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and value > 0


def _is_baud(value: Any) -> bool:
    return value is None or (isinstance(value, int) and not isinstance(value, bool) and value > 0)


def _reparse(argv: list[str]) -> argparse.Namespace | None:
    """Parse a stored command line with today's parser (``None`` if it no longer parses)."""
    from mbmon.cli import build_parser

    parser = build_parser()
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        try:
            args, _rest = parser.parse_known_args(argv)
        except SystemExit:
            return None
    return args


def recorded_annotator(log: McapLog, opts: RecordedOptions) -> Any:
    """The annotator for the profiles stored in the log, bound as they were recorded.

    Each ``--profile`` spec of the recording names a profile; its text is taken
    from the log's attachment (never from today's files: they may have changed
    or gone), parsed with ``loads_profile`` and bound with the same spec
    (``ProfileBinding.from_profiles``). The metadata's ``profile_bindings`` say
    which attachment each spec loaded; older logs fall back to matching names.
    ``None`` without profiles. A stored profile or spec that does not load is a
    :class:`LogError`.
    """
    stored = log.profiles()
    if not opts.profile_specs and not stored:
        return None
    from mbmon.semantics.annotate import Annotator
    from mbmon.semantics.profile import Profile, ProfileBinding, ProfileError, loads_profile

    meta = log.metadata.get(METADATA_NAME, {})
    try:
        bindings = {
            str(spec): int(number)
            for spec, number in json.loads(meta.get("profile_bindings", "[]"))
        }
    except (ValueError, TypeError):
        bindings = {}
    loaded: dict[int, Profile] = {}  # one Profile per attachment, shared by its specs

    def attachment(number: int) -> Profile:
        if number not in loaded:
            name, text = stored[number]
            try:
                loaded[number] = loads_profile(
                    text, file=f"{log.path} (stored profile {name})", path=f"log:{name}"
                )
            except ProfileError as exc:
                raise LogError(str(exc)) from None
        return loaded[number]

    by_name: dict[str, int] = {}
    for number, (name, _text) in enumerate(stored):
        by_name.setdefault(Path(name).stem, number)
    bound: list[tuple[str, Profile]] = []
    for spec in opts.profile_specs:
        _target, eq, name = spec.rpartition("=")
        found = bindings.get(spec)
        if found is None or not 0 <= found < len(stored):
            found = _stored_number_for(name.strip() if eq else spec.strip(), by_name)
        if found is None:
            raise LogError(
                f"{log.path}: profile {spec!r} was in force when recording but "
                "is not stored in the log"
            )
        bound.append((spec, attachment(found)))
    if not opts.profile_specs:  # no specs recorded: every stored profile, the last as default
        bound = [(name.replace("=", "_"), attachment(i)) for i, (name, _t) in enumerate(stored)]
    try:
        return Annotator(ProfileBinding.from_profiles(bound))
    except ProfileError as exc:
        raise LogError(f"{log.path}: recorded {exc}") from None


def _stored_number_for(name: str, numbers: Mapping[str, int]) -> int | None:
    """The attachment a spec's profile name matches (name, then file stem, else the only one)."""
    if name in numbers:
        return numbers[name]
    stem = Path(name).stem
    if stem in numbers:
        return numbers[stem]
    if len(numbers) == 1:
        return next(iter(numbers.values()))
    return None


def stored_profile_names(log: McapLog) -> list[str]:
    meta = log.metadata.get(METADATA_NAME, {})
    try:
        names = json.loads(meta.get("profiles", "[]"))
    except ValueError:
        names = []
    return [str(n) for n in names] if isinstance(names, list) else []


# --------------------------------------------------------------------------- filters

_OFFSET = re.compile(r"^\+?\s*((?:\d+(?:\.\d*)?|\.\d+)\s*(?:ms|min|s|m|h)?\s*)+$")
_PART = re.compile(r"(\d+(?:\.\d*)?|\.\d+)\s*(ms|min|s|m|h)?")
_UNIT = {"ms": 0.001, "s": 1.0, "": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}


class FilterError(ValueError):
    """A filter value that cannot be understood (a usage error)."""


def parse_when(text: str, start: float | None) -> float:
    """A ``--since``/``--until`` value as epoch seconds.

    Accepts an offset from the start of the log (``+5s``, ``+1m30s``, ``+250ms``,
    ``+2.5``: seconds), an ISO 8601 date and time (local time unless it says
    otherwise), a time of day (``12:00:05``, on the log's first day) or epoch
    seconds (a number of 9 digits or more).
    """
    value = text.strip()
    if not value:
        raise FilterError("empty time")
    if value.startswith("+") or (
        _OFFSET.match(value) and not re.fullmatch(r"\d{9,}(\.\d*)?", value)
    ):
        if not _OFFSET.match(value):
            raise FilterError(f"not an offset: {text!r} (e.g. +5s, +1m30s, +250ms)")
        offset = sum(float(n) * _UNIT[u] for n, u in _PART.findall(value))
        if start is None:
            raise FilterError("the log has no records to measure an offset from")
        return start + offset
    if re.fullmatch(r"\d{9,}(\.\d*)?", value):
        return float(value)
    if re.fullmatch(r"\d{1,2}:\d{2}(:\d{2}(\.\d+)?)?", value):
        if start is None:
            raise FilterError("the log has no records to take the day from")
        day = _dt.datetime.fromtimestamp(start).date()
        clock = _dt.time.fromisoformat(value if value.count(":") == 2 else value + ":00")
        return _dt.datetime.combine(day, clock).timestamp()
    try:
        moment = _dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        raise FilterError(
            f"not a time: {text!r} (use +5s, 12:00:05, 2024-05-01T12:00:05 or epoch seconds)"
        ) from None
    return moment.timestamp()


def parse_int(text: str) -> int:
    try:
        return int(text.strip(), 0)
    except ValueError:
        raise FilterError(f"not a number: {text!r}") from None


def parse_fcs(text: str) -> frozenset[int]:
    """``--fc 3,0x10`` -> {3, 16}."""
    out = {parse_int(part) for part in text.split(",") if part.strip()}
    if not out or any(not 0 <= fc <= 0xFF for fc in out):
        raise FilterError(f"function codes are 1..127: {text!r}")
    return frozenset(fc & 0x7F for fc in out)


def parse_range(text: str) -> tuple[int, int]:
    """``--address 200`` or ``200-251`` (inclusive; 0x.. accepted)."""
    first, dash, last = text.partition("-")
    lo = parse_int(first)
    hi = parse_int(last) if dash else lo
    if lo > hi or lo < 0 or hi > 0xFFFF:
        raise FilterError(f"not an address range A[-B] within 0..65535: {text!r}")
    return lo, hi


@dataclass(slots=True)
class RecordFilter:
    """The replay/export filters; an unset filter lets everything through.

    Frame filters (unit, function code, address) let only records that have
    those fields through: events pass only when no frame filter is set.
    """

    units: frozenset[int] | None = None
    fcs: frozenset[int] | None = None
    address: tuple[int, int] | None = None
    since: float | None = None
    until: float | None = None
    grep: str | None = None

    @property
    def active(self) -> bool:
        return any(
            v is not None
            for v in (self.units, self.fcs, self.address, self.since, self.until, self.grep)
        )

    def matches(self, obj: Mapping[str, Any] | None, line: str, ts: float) -> bool:
        if self.since is not None and ts < self.since:
            return False
        if self.until is not None and ts > self.until:
            return False
        if self.grep is not None and self.grep.lower() not in line.lower():
            return False
        if self.units is None and self.fcs is None and self.address is None:
            return True
        if obj is None:
            return False
        if self.units is not None and obj.get("unit") not in self.units:
            return False
        if self.fcs is not None and obj.get("fc") not in self.fcs:
            return False
        return self.address is None or touches(obj, *self.address)


def touches(obj: Mapping[str, Any], lo: int, hi: int) -> bool:
    """Whether a frame's register/coil range (or 0x17's write range) meets [lo, hi]."""
    spans = []
    address = obj.get("address")
    if isinstance(address, int):
        count = obj.get("count")
        n = count if isinstance(count, int) and count > 0 else 1
        spans.append((address, address + n - 1))
    fields = obj.get("fields")
    if isinstance(fields, Mapping) and isinstance(fields.get("write_address"), int):
        wa = fields["write_address"]
        wc = fields.get("write_count")
        spans.append((wa, wa + (wc if isinstance(wc, int) and wc > 0 else 1) - 1))
    return any(a <= hi and b >= lo for a, b in spans)


# --------------------------------------------------------------------------- pacing


class Pacer:
    """Hold output back to ``speed`` times the original pace.

    Every record's due time is computed from one monotonic start and the first
    record's capture time (start + (ts - ts0) / speed), so sleeping late once
    never accumulates into drift over a long replay.
    """

    def __init__(
        self,
        speed: float,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if speed <= 0:
            raise ValueError("speed must be > 0")
        self.speed = speed
        self._clock = clock
        self._sleep = sleep
        self._start: float | None = None
        self._ts0 = 0.0

    def wait(self, ts: float) -> None:
        """Return when the record captured at ``ts`` is due."""
        if self._start is None:
            self._start = self._clock()
            self._ts0 = ts
            return
        due = self._start + (ts - self._ts0) / self.speed
        delay = due - self._clock()
        if delay > 0:
            self._sleep(delay)


def first_record_time(log: McapLog) -> float | None:
    """Capture time of the first record (the origin of ``+5s`` offsets)."""
    span = log.time_span
    if span is not None:
        return span[0] / 1e9
    for msg in log.messages((*RECORD_TOPICS, TOPIC_MONITOR, TOPIC_RAW)):
        return msg.log_time / 1e9
    return None


def iter_filtered(records: Iterable[LoggedRecord], flt: RecordFilter) -> Iterator[LoggedRecord]:
    for rec in records:
        if flt.matches(rec.obj, rec.text, rec.time):
            yield rec
