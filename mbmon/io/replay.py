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
  their stored command line, read by :func:`argv_settings`, not the CLI's
  parser: ``mbmon.io`` never imports ``mbmon.cli``) and attachments;
- :func:`first_record_time` is the origin of ``--since +5s`` and ``-t r``.

The filters and the ``--speed`` pace live in :mod:`mbmon.filters` (re-exported
here for older callers).
"""

from __future__ import annotations

import base64
import json
import math
import re
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mbmon.filters import (  # noqa: F401  (re-exported: their home is mbmon.filters)
    FilterError,
    Pacer,
    RecordFilter,
    iter_filtered,
    parse_fcs,
    parse_int,
    parse_range,
    parse_when,
    touches,
)
from mbmon.io.mcap.layout import (
    METADATA_NAME,
    RECORD_TOPICS,
    SOURCE_EVENTS,
    TOPIC_FRAMES,
    TOPIC_MONITOR,
    TOPIC_RAW,
    frame_chunk,
    full_frame_object,
)
from mbmon.io.mcap.payloads import payload_problem
from mbmon.io.mcap.reader import LogError, LogMessage, McapLog
from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.stored import StoredRecord, kind_of

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

    def stored(self) -> StoredRecord:
        """This record as the listeners take it (:class:`~mbmon.stored.StoredRecord`)."""
        return StoredRecord(self.index, self.time, kind_of(self.obj), None, obj=self.obj,
                            line=self.text)  # fmt: skip


def payload(log: McapLog, msg: LogMessage) -> dict[str, Any] | None:
    """The payload of ``msg`` when it can be trusted, else ``None``: every reader of a
    log asks here. A payload that is not JSON or does not match its topic's schema
    (:func:`~mbmon.io.mcap.payloads.payload_problem`) is left out and recorded with
    where it is (:meth:`McapLog.skip`); the commands report it and exit 1.

    A /modbus/frames object comes in format 1's shape whatever the log's format
    (:func:`~mbmon.io.mcap.layout.full_frame_object`; its ``line`` is the monitor
    message's, which :func:`logged_records` fills in)."""
    data = stored_payload(log, msg)
    if data is not None and msg.topic == TOPIC_FRAMES:
        return full_frame_object(data)
    return data


def stored_payload(log: McapLog, msg: LogMessage) -> dict[str, Any] | None:
    """:func:`payload` as the log stores it: a /modbus/frames object as its format has
    it (format 4's ``chunk`` member kept, for the readers of chunks)."""
    data, why = msg.decode()
    if why is None:
        why = payload_problem(msg.topic, data)
    if why is not None:
        log.skip(msg, why)
        return None
    return data  # type: ignore[no-any-return]  # an object: payload_problem said so


def logged_records(log: McapLog) -> Iterator[LoggedRecord]:
    """Every record of the log in record order (see the module docstring); a damaged
    message is left out (:func:`payload`), its record shown by what else it has.
    A frames object of format 2 gets its ``line`` from the record's monitor message."""
    for record in _merged_records(log):
        obj = record.obj
        if obj is not None and obj.get("line") is None and record.line is not None:
            obj["line"] = record.line
        yield record


def _merged_records(log: McapLog) -> Iterator[LoggedRecord]:
    """:func:`logged_records` before the lines of format 2's frames objects are filled in."""
    current: LoggedRecord | None = None
    for msg in log.messages((*RECORD_TOPICS, TOPIC_MONITOR)):
        data = payload(log, msg)
        if data is None:
            continue
        if msg.topic == TOPIC_MONITOR:
            index = data.get("line")
            if index is None:
                log.skip(msg, "monitor line without its record index")
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
        if index is None:
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
        data = payload(log, msg)
        if data is not None and data.get("index") is None and data.get("event") == "stats":
            last = data.get("info")
    return last


#: the key of a ``modbus.Frame``'s field 21 (``chunk``, log format 4) in any wire type: a
#: message without it stands for no chunk, and is not decoded here
_CHUNK_KEY = re.compile(b"[\xa8-\xaf]\x01")


def raw_items(log: McapLog) -> Iterator[Chunk | Event]:
    """The chunks and source events of ``/modbus/raw``, in capture order, with the
    chunks format 4 left out rebuilt where their frame's message is (its ``chunk``:
    :func:`~mbmon.io.mcap.layout.frame_chunk`); a damaged message is left out
    (:func:`payload`: a damaged frame message loses its chunk) and the rest goes on."""
    streams: dict[int, Stream] = {}
    search = _CHUNK_KEY.search
    for msg in log.messages([TOPIC_RAW, TOPIC_FRAMES]):
        if msg.topic == TOPIC_FRAMES:
            if msg.decoder is None or search(msg.raw) is None:
                continue  # no chunk of format 4 (JSON frames are formats 1 and 2)
            frame = stored_payload(log, msg)
            if frame is None or "chunk" not in frame:
                continue
            try:
                data = frame_chunk(frame)
            except ValueError as exc:  # payload_problem asked the same: not met
                log.skip(msg, f"damaged /modbus/frames message: {exc}")
                continue
            if data is None:
                continue
        else:
            data = stored_payload(log, msg)
        if data is None:
            continue
        try:
            item = _raw_item(data, streams)
        except (KeyError, ValueError, TypeError) as exc:
            log.skip(msg, f"damaged /modbus/raw message: {exc}")
            continue
        yield item


def _raw_item(data: dict[str, Any], streams: dict[int, Stream]) -> Chunk | Event:
    """One ``/modbus/raw`` payload (its types checked against the schema) as a chunk or
    source event; what the schema leaves open but an item needs raises ``ValueError``."""
    sid = data.get("stream")
    stream: Stream | None = None
    if sid is not None:
        stream = streams.get(sid)
        if stream is None:
            client, server = data.get("client"), data.get("server")
            if client is None or server is None:
                raise ValueError(f"stream {sid} without its endpoints")
            stream = Stream(
                sid, Transport(data["transport"]), client, server, data.get("timed") is not False
            )
            streams[sid] = stream
    ts = float(data["ts"])
    if data.get("type") == "event":
        kind = EventKind(data["event"])
        if kind not in SOURCE_EVENTS:
            raise ValueError(f"a {kind.value} event is not a source event")
        return Event(ts, stream, kind, _source_info(data.get("info") or {}))
    if stream is None:
        raise ValueError("chunk without a stream")
    direction = Direction(data["direction"])
    if direction is Direction.BUS and not stream.transport.is_rtu:  # a bus carries RTU only
        raise ValueError(f"direction bus on a {stream.transport.value} stream")
    return Chunk(ts, stream, direction, base64.b64decode(data["data"]))


#: the fields of a source event's info the decoders and writers read, and their types
_SOURCE_INFO: dict[str, type[Any]] = {
    "how": str, "by": str, "message": str, "direction": str, "bytes": int, "half_closed": bool,
}  # fmt: skip


def _source_info(info: dict[str, Any]) -> dict[str, Any]:
    """A source event's info as the pipeline may trust it: the fields it reads have their
    types (else ``ValueError``); other fields only plain values (the rest dropped)."""
    out: dict[str, Any] = {}
    value: Any
    for key, value in info.items():
        wanted = _SOURCE_INFO.get(key)
        if wanted is not None:
            if type(value) is not wanted:
                raise ValueError(f"info.{key} is not a {wanted.__name__}")
            if key == "direction":
                Direction(value)
            elif key == "bytes" and not 0 <= value < 1 << 32:
                raise ValueError(f"info.bytes out of range: {value}")
            out[key] = value
        elif isinstance(value, str | bool | int | None) or (
            isinstance(value, float) and math.isfinite(value)
        ):
            out[key] = value
    return out


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
    recovered from its stored ``command_line`` (:func:`argv_settings`).
    """
    meta = log.metadata.get(METADATA_NAME, {})
    opts = RecordedOptions()
    line = _json_value(meta.get("command_line", "[]"))
    if isinstance(line, list):
        opts.command_line = [x for x in line if isinstance(x, str)]  # others are damage
    opts.robot = meta.get("robot") or None
    opts.robot_is_client = meta.get("robot_is_client") == "true"
    specs = _stored(meta, "profile_specs", _is_spec_list)
    timeout = _stored(meta, "timeout", _is_timeout)
    baud = _stored(meta, "baud", _is_baud)
    if _MISSING in (specs, timeout, baud) and len(opts.command_line) > 1:
        parsed = argv_settings(opts.command_line[1:])  # an older log: the command line says
        if specs is _MISSING:
            specs = parsed["profile"]
        if timeout is _MISSING:
            timeout = parsed.get("timeout", 1.0)
        if baud is _MISSING:
            baud = parsed.get("baud")
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
    value = _json_value(text)
    return value if value is not _MISSING and valid(value) else _MISSING


def _json_value(text: str) -> Any:
    """A metadata value's JSON, or ``_MISSING`` when it is not JSON (or nests too deeply)."""
    try:
        return json.loads(text)
    except (ValueError, RecursionError):
        return _MISSING


def _is_spec_list(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(spec, str) for spec in value)


def _is_timeout(value: Any) -> bool:
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and 0 < value <= 1e6  # seconds; a larger value is damage, not a timeout
    )


def _is_baud(value: Any) -> bool:
    return value is None or (
        isinstance(value, int) and not isinstance(value, bool) and 0 < value <= 100_000_000
    )


#: options of the recording command (``read``) that take a value, for reading its stored
#: command line; the value of any other option is never mistaken for one of these
_VALUE_OPTIONS = (
    "--robot", "--profile", "--write", "--port", "--rtu-port", "--rtu-raw", "--timeout", "--baud",
)  # fmt: skip
_SHORT_VALUE_OPTIONS = {"-w": "--write"}


def argv_settings(argv: list[str]) -> dict[str, Any]:
    """The analysis settings in a stored ``read`` command line (without the program name):
    ``profile`` (every ``--profile`` value, in order), ``timeout`` and ``baud`` (the last
    valid value, when given), read as argparse would (``--opt value``, ``--opt=value``,
    unambiguous abbreviations, ``--`` ends the options) without importing the CLI."""
    out: dict[str, Any] = {"profile": []}
    i = 0
    while i < len(argv):
        token = argv[i]
        i += 1
        if token == "--":
            break
        if not token.startswith("-") or token == "-":
            continue
        value: str | None = None
        if token.startswith("--"):
            name, eq, rest = token.partition("=")
            if eq:
                value = rest
            if name not in _VALUE_OPTIONS:
                matches = [o for o in _VALUE_OPTIONS if o.startswith(name)]
                if len(matches) != 1:
                    continue  # another option (a flag): nothing to take
                name = matches[0]
        elif token[:2] in _SHORT_VALUE_OPTIONS:
            name = _SHORT_VALUE_OPTIONS[token[:2]]
            value = token[2:] or None
        else:
            continue
        if value is None:
            if i >= len(argv):
                break
            value = argv[i]
            i += 1
        if name == "--profile":
            out["profile"].append(value)
        elif name == "--timeout":
            try:
                timeout = float(value)
            except ValueError:
                continue
            if _is_timeout(timeout):
                out["timeout"] = timeout
        elif name == "--baud":
            try:
                baud = int(value)
            except ValueError:
                continue
            if _is_baud(baud):
                out["baud"] = baud
    return out


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
            for spec, number in _json_value(meta.get("profile_bindings", "[]"))
        }
    except (ValueError, TypeError):  # not pairs of a spec and a number (_MISSING too)
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
    names = _json_value(meta.get("profiles", "[]"))
    return [n for n in names if isinstance(n, str)] if isinstance(names, list) else []


def first_record_time(log: McapLog) -> float | None:
    """Capture time of the first record (the origin of ``+5s`` offsets): from the
    statistics of a finished log, else the first readable message's. ``None`` when
    no chunk can be read: the damage is in :attr:`McapLog.status`, and the read
    that follows reports it."""
    span = log.time_span
    if span is not None:
        return span[0] / 1e9
    try:
        for msg in log.messages((*RECORD_TOPICS, TOPIC_MONITOR, TOPIC_RAW)):
            return msg.log_time / 1e9
    except LogError:
        pass
    return None
