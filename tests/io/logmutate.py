"""Hostile MCAP logs for the log commands, and the commands run on them in-process.

Shared by the CI fuzz test (``test_log_commands_fuzz.py``, hypothesis drives the
``random.Random`` every mutation draws from) and the offline campaign (run this
file: ``python3 tests/io/logmutate.py --logs 100000 --seed 1``), so both mutate
logs the same two ways:

- **blind**: bytes of a real, zstd-compressed log (finished, or cut as a
  ``kill -9`` leaves it) flipped, overwritten in bursts, inserted, deleted, or
  the file truncated;
- **structure-aware**: the same messages rewritten into a log of uncompressed
  chunks without CRCs (so damage reaches the payload parsers instead of being
  stopped by a chunk CRC), with JSON payloads, metadata values and attachments
  mutated: wrong types, integers beyond 64 bits, missing keys, nested garbage,
  deep nesting, bytes that are not JSON or not UTF-8; then, sometimes, bytes of
  the file flipped or the file cut.

:func:`run_commands` runs ``replay``, ``replay --json``, ``replay --redecode``,
``info``, ``info --json`` and ``export`` (each output format in turn) through
their ``run_*`` functions and returns what escaped each: nothing may.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import io
import itertools
import json
import random
import signal
import struct
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script from anywhere: this tree's mbmon
    sys.path.insert(0, str(ROOT))

_REC = struct.Struct("<BQ")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
MAGIC_LEN = 8

#: captures of the project (captures/) a base log is recorded from, with the profile in force
BASE_CAPTURES = (
    ("hrss_ptp.pcap", ["hrss"]),
    ("hrss_rtu.pcap", ["hrss"]),
    ("sim_exceptions.pcap", []),
    ("demo.pcap", ["hrss"]),
)


@dataclass(frozen=True, slots=True)
class BaseLog:
    """One recorded log: its zstd file bytes, the same cut before its summary, and its parts."""

    name: str
    finished: bytes
    unfinished: bytes
    messages: list[tuple[str, int, bytes]]  # (topic, log time, payload) in file order
    metadata: dict[str, dict[str, str]]
    attachments: list[tuple[str, str, bytes, int]]  # name, media type, data, log time


def record_base_logs(tmp: Path, chunk_size: int = 3000, items: int | None = None) -> list[BaseLog]:
    """Record every capture of :data:`BASE_CAPTURES` with the MCAP sink (small chunks,
    zstd as ``read -w`` writes) and keep each log's bytes and messages; ``items``: only
    the first so many packets and events of each capture (shorter logs, read faster)."""
    from mbmon.commands.common import make_annotator, profile_sources
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.io.mcap.reader import McapLog
    from mbmon.pipeline import Pipeline
    from mbmon.sinks.base import SinkContext
    from mbmon.sinks.mcap import McapSink
    from mbmon.sources.pcapfile import read_capture

    out = []
    for capture, specs in BASE_CAPTURES:
        src = ROOT / "captures" / capture
        if not src.exists():
            continue
        annotator = make_annotator(specs) if specs else None
        path = tmp / (Path(capture).stem + ".mcap")
        ctx = SinkContext(
            view=View(),
            command_line=["mbmon", "read", str(src), *(f"--profile={s}" for s in specs)],
            source=str(src),
            profiles=profile_sources(annotator),
            profile_specs=list(specs),
        )
        with Hub(Pipeline(annotator)) as hub:
            hub.add_listener(McapSink(path, ctx, chunk_size=chunk_size))
            hub.run_items(itertools.islice(read_capture(src), items))
        data = path.read_bytes()
        with McapLog(path) as log:
            messages = [(m.topic, m.log_time, m.raw) for m in log.messages()]
            metadata = {k: dict(v) for k, v in log.metadata.items()}
            attachments = [(a.name, a.media_type, a.data, a.log_time) for a in log.attachments]
        out.append(
            BaseLog(path.stem, data, data[: summary_start(data)], messages, metadata, attachments)
        )
    if not out:
        raise FileNotFoundError(f"no capture of {BASE_CAPTURES} in {ROOT / 'captures'}")
    return out


def summary_start(data: bytes | bytearray) -> int:
    """Where the summary section of a finished log starts (the footer's first field):
    the log cut there is what a ``kill -9`` before ``close`` leaves."""
    return int(_U64.unpack_from(data, len(data) - MAGIC_LEN - 20)[0])


# --------------------------------------------------------------------------- blind


def blind(base: BaseLog, rng: random.Random) -> bytes:
    """The zstd log (finished or unfinished) with a few random byte-level damages.

    Half the damages land anywhere; the other half inside a top-level record picked
    with equal odds (so the small records a reader trusts most, the footer, summary
    offsets, chunk indexes and statistics, are hit as often as the schemas and
    attachments that fill most of the file)."""
    data = bytearray(base.finished if rng.random() < 0.6 else base.unfinished)
    records = walk(bytes(data))
    for _ in range(rng.choice((1, 1, 1, 2, 3, 8))):
        at = None
        if records and rng.random() < 0.5:
            p, _op, length = rng.choice(records)
            at = rng.randrange(p, p + 9 + length)
        _damage_bytes(data, rng, start=MAGIC_LEN if rng.random() < 0.97 else 0, at=at)
    return bytes(data)


def _damage_bytes(
    data: bytearray, rng: random.Random, start: int = MAGIC_LEN, at: int | None = None
) -> None:
    """One damage at ``at`` (or a random place from ``start`` on)."""
    if len(data) <= start + 1:
        return
    if at is None or not start <= at < len(data):
        at = rng.randrange(start, len(data))
    kind = rng.randrange(7)
    if kind == 0:  # one bit
        data[at] ^= 1 << rng.randrange(8)
    elif kind == 1:  # one byte
        data[at] = rng.randrange(256)
    elif kind == 2:  # a burst of random or extreme bytes
        n = rng.choice((2, 4, 8, 16, 64))
        data[at : at + n] = rng.choice(
            (rng.randbytes(n), b"\xff" * n, b"\x00" * n, b"\x7f" + b"\xff" * (n - 1))
        )
    elif kind == 3:  # bytes inserted
        data[at:at] = rng.randbytes(rng.choice((1, 3, 9, 100)))
    elif kind == 4:  # bytes deleted
        del data[at : at + rng.choice((1, 4, 9, 100))]
    elif kind == 5:  # the file cut short
        del data[at:]
    else:  # a little-endian length-like field overwritten
        width = rng.choice((4, 8))
        value = rng.choice((0, 1, 9, (1 << (8 * width)) - 1, 1 << 31, rng.randrange(len(data))))
        value &= (1 << (8 * width)) - 1
        data[at : at + width] = value.to_bytes(width, "little")


# --------------------------------------------------------------------------- structure-aware

_KEYS = (
    "index", "time", "kind", "fc", "unit", "stream", "line", "message", "level", "pdu",
    "transport", "client", "server", "direction", "ts", "data", "type", "event", "info",
    "command", "phase", "text", "duration", "latency_ms", "crc_ok", "malformed",
    "exception_code", "request_index", "address", "values", "timed", "name", "file",
)  # fmt: skip


def garbage(rng: random.Random, depth: int = 0) -> Any:
    """A JSON value chosen to break code that trusts a field's type or range."""
    choices: list[Callable[[], Any]] = [
        lambda: None,
        lambda: rng.choice((True, False)),
        lambda: rng.choice((0, -1, 1, 255, 65536, 2**31, 2**53 + 1, 2**63 - 1, 2**63, 2**64)),
        lambda: rng.choice((2**64 + 1, -(2**63) - 1, 10**30, -(10**30), 10**400)),
        lambda: rng.choice((0.5, -1e300, 1e308, 1e-320, float("inf"), float("-inf"))),
        lambda: float("nan"),
        lambda: rng.choice(("", "x", "03", "request", "tcp", "rtu", "\udcff", "\x00", "é" * 50)),
        lambda: rng.choice(("2024-05-01", "12:00:05", "+5s", "ff ff", "0x10", "-1", "1e999")),
        lambda: "A" * rng.choice((1, 1000, 100_000)),
    ]
    if depth < 3:
        choices += [
            lambda: [garbage(rng, depth + 1) for _ in range(rng.randrange(4))],
            lambda: {rng.choice(_KEYS): garbage(rng, depth + 1) for _ in range(rng.randrange(4))},
        ]
    return rng.choice(choices)()


def mutate_obj(obj: Any, rng: random.Random) -> Any:
    """A decoded payload with one to three fields given the wrong type, range or absence."""
    if not isinstance(obj, dict) or rng.random() < 0.08:
        return garbage(rng)
    obj = dict(obj)
    for _ in range(rng.choice((1, 1, 2, 3))):
        keys = list(obj)
        what = rng.randrange(4)
        if what == 0 and keys:  # a key missing
            del obj[rng.choice(keys)]
        elif what == 1 and keys:  # a key's value replaced
            obj[rng.choice(keys)] = garbage(rng)
        elif what == 2:  # a key the reader looks for, added with a hostile value
            obj[rng.choice(_KEYS)] = garbage(rng)
        elif keys:  # a nested value's own fields mutated
            key = rng.choice(keys)
            obj[key] = mutate_obj(obj[key], rng) if isinstance(obj[key], dict) else garbage(rng)
    return obj


def register(writer: Any, topic: str, encoding: str | None = None) -> int:
    """A channel for ``topic`` as a format-3 log declares it: /modbus/frames and
    /modbus/raw protobuf with their schema (``encoding``: another message encoding on
    it), every other topic JSON without a schema."""
    from mbmon.io.mcap.layout import PROTO_TOPICS, channel_schema

    if topic in PROTO_TOPICS:
        name, schema_encoding, data, message_encoding = channel_schema(topic)
        sid = writer.register_schema(name, schema_encoding, data)
        return writer.register_channel(topic, encoding or message_encoding, sid)
    return writer.register_channel(topic, encoding or "json", 0)


def payload_obj(topic: str, raw: bytes) -> Any:
    """A base log's payload as readers see it (format 3's protobuf topics decoded)."""
    from mbmon.io.mcap.layout import PROTO_TOPICS
    from mbmon.io.mcap.proto import decode_payload

    if topic in PROTO_TOPICS:
        return decode_payload(PROTO_TOPICS[topic], "protobuf", raw)
    return json.loads(raw)


def payload_bytes(topic: str, obj: Any) -> bytes:
    """An object as a format-3 log stores it on ``topic`` (protobuf or JSON)."""
    from mbmon.io.mcap.proto import encode_frame, encode_raw

    if topic == "/modbus/frames" and isinstance(obj, dict):
        return encode_frame(obj)
    if topic == "/modbus/raw" and isinstance(obj, dict):
        return encode_raw(obj)
    return json.dumps(obj).encode("utf-8", "surrogatepass")


def deep_payload(topic: str) -> bytes:
    """A payload nested deeper than a parser recurses (protobuf: in its extra JSON)."""
    from mbmon.io.mcap.layout import PROTO_TOPICS
    from mbmon.io.mcap.proto import varint

    if topic in PROTO_TOPICS:
        text = b'{"fields":' + b"[" * 100_000
        return b"\xf2\x01" + varint(len(text)) + text
    return b"[" * 100_000


#: format 4's chunk marker (``modbus.Frame`` field 21) as the writers end a frame with it
_MARKS = (b"\xaa\x01\x03c2s", b"\xaa\x01\x03s2c")


def mutate_marker(raw: bytes, rng: random.Random) -> bytes:
    """A /modbus/frames message (format 4) with its chunk marker damaged: a wrong value, a
    wrong wire type, a marker on a frame that lacks what the chunk is rebuilt from (its
    tid, unit, pdu, time, endpoints) or that stands for no chunk (noise), a marker twice."""
    body = raw[:-6] if raw[-6:] in _MARKS else raw
    mark = raw[-6:] if raw[-6:] in _MARKS else rng.choice(_MARKS)
    r = rng.random()
    if r < 0.25:  # a value that is no direction (or no UTF-8, or cut)
        from mbmon.io.mcap.proto import varint

        value = rng.choice((b"bus", b"C2S", b"", b"c2s\x00", b"\xff\xfe", b"x" * 300))
        return body + b"\xaa\x01" + varint(len(value)) + value
    if r < 0.45:  # another wire type: a varint, a double, a 32-bit, a group, cut short
        return body + rng.choice(
            (b"\xa8\x01\x05", b"\xa9\x01" + bytes(8), b"\xad\x01" + bytes(4), b"\xab\x01",
             b"\xaa\x01\x09c2s", b"\xaa\x01")
        )  # fmt: skip
    if r < 0.55:
        return body + mark + mark
    try:
        obj = payload_obj("/modbus/frames", body)
    except ValueError:
        return body + mark
    if not isinstance(obj, dict):
        return body + mark
    for key in rng.sample(("tid", "unit", "pdu", "time", "src", "dst", "stream", "transport"), 2):
        if rng.random() < 0.5:
            obj.pop(key, None)
        else:
            obj[key] = rng.choice((None, -1, 1 << 70, "x", 1.5, "ZZ"))
    return payload_bytes("/modbus/frames", obj) + mark


def mutate_proto(topic: str, raw: bytes, rng: random.Random) -> bytes:
    """A protobuf payload (format 3 or 4) mutated as bytes or as the object it holds
    (format 4's chunk marker as well: :func:`mutate_marker`)."""
    r = rng.random()
    if topic == "/modbus/frames" and (raw[-6:] in _MARKS or r < 0.05) and rng.random() < 0.4:
        return mutate_marker(raw, rng)
    if r < 0.1:
        return rng.choice((b"", b"\xff" * 11, raw[: len(raw) // 2], deep_payload(topic)))
    if r < 0.3:
        data = bytearray(raw)
        for _ in range(rng.choice((1, 2, 5))):
            if data:
                at = rng.randrange(len(data))
                data[at] = rng.choice((0, 0x7F, 0x80, 0xFF, rng.randrange(256)))
        return bytes(data)
    try:
        obj = payload_obj(topic, raw)
    except ValueError:
        return raw
    return payload_bytes(topic, mutate_obj(obj, rng))


def mutate_payload(raw: bytes, rng: random.Random, topic: str = "") -> bytes:
    """A message payload mutated as JSON (mostly) or as bytes; a protobuf one of
    ``topic`` (format 3's /modbus/frames and /modbus/raw) by :func:`mutate_proto`."""
    from mbmon.io.mcap.layout import PROTO_TOPICS

    if topic in PROTO_TOPICS and not raw.startswith(b"{"):
        return mutate_proto(topic, raw, rng)
    r = rng.random()
    if r < 0.06:  # not JSON, not UTF-8, or nested deeper than any parser recurses
        return rng.choice(
            (b"", b"{", b"\xff\xfe", raw[: len(raw) // 2], b"[" * 100_000, b'{"a":' * 5000)
        )
    if r < 0.12:  # a raw chunk's base64 damaged
        try:
            obj = json.loads(raw)
            if isinstance(obj, dict) and isinstance(obj.get("data"), str):
                obj["data"] = rng.choice(("!!", "A", base64.b64encode(rng.randbytes(9)).decode()))
                return json.dumps(obj).encode()
        except ValueError:
            pass
    try:
        obj = json.loads(raw)
    except ValueError:
        return raw
    return json.dumps(mutate_obj(obj, rng), ensure_ascii=rng.random() < 0.5).encode(
        "utf-8", "surrogatepass"
    )


def structured(base: BaseLog, rng: random.Random) -> bytes:
    """The log's messages rewritten into uncompressed, CRC-less chunks, payloads mutated."""
    from mbmon.io.mcap.writer import McapFileWriter

    rate = rng.choice((0.01, 0.05, 0.2, 1.0))
    metadata = {k: dict(v) for k, v in base.metadata.items()}
    if rng.random() < 0.3:
        meta = metadata.setdefault("mbmon", {})
        for _ in range(rng.randrange(1, 4)):
            key = rng.choice(
                ("command_line", "profile_specs", "profile_bindings", "profiles", "timeout",
                 "baud", "robot", "robot_is_client", "source", "version", "started")
            )  # fmt: skip
            if rng.random() < 0.2:
                meta.pop(key, None)
            else:
                meta[key] = json.dumps(garbage(rng))
    attachments = list(base.attachments)
    if attachments and rng.random() < 0.15:
        name, media, data, t = attachments[0]
        data = bytearray(data)
        _damage_bytes(data, rng, start=0)
        attachments[0] = (name, media, bytes(data), t)
    buf = io.BytesIO()
    writer = McapFileWriter(buf, chunk_size=rng.choice((300, 1000, 5000)))
    writer.compression, writer._compress = "", None
    writer.start(library="mbmon fuzz")
    for name, data in metadata.items():
        writer.add_metadata(name, data)
    for name, media, data, t in attachments:
        writer.add_attachment(0, t, name, media, data)
    channels: dict[str, int] = {}
    for topic, log_time, raw in _reshuffled(base.messages, rng):
        if topic not in channels:
            encoding = None if rng.random() < 0.99 else rng.choice(("", "cbor", "JSON", "json"))
            channels[topic] = register(writer, topic, encoding)
        if rng.random() < rate:
            raw = mutate_payload(raw, rng, topic)
        if rng.random() < 0.01:
            log_time = rng.choice((0, 1, 2**63, 2**64 - 1))
        writer.add_message(channels[topic], log_time, raw)
    writer.finish()
    data = buf.getvalue()
    if rng.random() < 0.25:  # as a kill -9 leaves it: no summary, maybe a chunk cut
        start = summary_start(data)
        data = data[: rng.randrange(start - 50, start + 1)]
    if rng.random() < 0.3:  # damage that reaches the record parsers (no chunk CRC stops it)
        damaged = bytearray(_without_crcs(data))
        for _ in range(rng.choice((1, 2, 5))):
            _damage_bytes(damaged, rng)
        data = bytes(damaged)
    return data


#: topics a message may be moved to: mbmon's, and some no mbmon version writes
_TOPICS = (
    "/modbus/raw", "/modbus/frames", "/modbus/monitor", "/hrss/state", "/hrss/commands",
    "/mbmon/events", "/modbus/raw2", "", "/x" * 300,
)  # fmt: skip


def _reshuffled(
    messages: list[tuple[str, int, bytes]], rng: random.Random
) -> list[tuple[str, int, bytes]]:
    """The messages, on most logs as they are; on some, a few moved to another topic
    (a payload of the wrong schema, or an unknown topic), dropped, repeated or swapped
    with the next (record indexes out of order, requests without their response)."""
    rate = rng.choice((0.0, 0.0, 0.0, 0.01, 0.1))
    if not rate:
        return messages
    out = list(messages)
    i = 0
    while i < len(out):
        if rng.random() < rate:
            _topic, log_time, raw = out[i]
            what = rng.randrange(4)
            if what == 0:
                out[i] = (rng.choice(_TOPICS), log_time, raw)
            elif what == 1:
                del out[i]
                continue
            elif what == 2:
                out.insert(i, out[i])
                i += 1
            elif i + 1 < len(out):
                out[i], out[i + 1] = out[i + 1], out[i]
        i += 1
    return out


def walk(data: bytes) -> list[tuple[int, int, int]]:
    """The top-level records of an undamaged file: (offset, opcode, body length)."""
    out = []
    p = MAGIC_LEN
    while p + 9 <= len(data):
        op, length = _REC.unpack_from(data, p)
        out.append((p, op, length))
        p += 9 + length
    return out


def _without_crcs(data: bytes) -> bytes:
    """The file (finished, or cut) with every chunk CRC and the summary CRC set to 0
    (MCAP: not computed); the payloads were mutated before the CRCs were computed, so
    only byte damage after this needs it."""
    out = bytearray(data)
    for p, op, length in walk(data):
        if p + 9 + length > len(data):
            break
        if op == 0x06:
            _U32.pack_into(out, p + 9 + 24, 0)
        elif op == 0x02:
            _U32.pack_into(out, p + 9 + 16, 0)
    return bytes(out)


def mutated(bases: list[BaseLog], rng: random.Random) -> tuple[str, bytes]:
    """One mutated log of either kind: (``"blind"`` or ``"structured"``, its bytes)."""
    base = rng.choice(bases)
    if rng.random() < 0.5:
        return "blind", blind(base, rng)
    return "structured", structured(base, rng)


# --------------------------------------------------------------------------- the commands

#: the command lines run on every mutated log (LOG and OUT filled in); ``export`` takes
#: one output format per log, in turn; ``exchanges`` is what ``replay --serve`` and
#: ``--to`` do with a log before they open a socket (:func:`serve_image`)
COMMANDS: tuple[tuple[str, ...], ...] = (
    ("replay", "LOG"),
    ("replay", "LOG", "--json"),
    ("replay", "LOG", "--redecode"),
    ("replay", "LOG", "--since", "+0.5s", "-t", "r"),
    ("info", "LOG"),
    ("info", "LOG", "--json"),
    ("export", "LOG", "-o", "OUT"),
    ("exchanges", "LOG"),
)
EXPORT_SUFFIXES = (".jsonl", ".csv", ".txt", ".pcap", ".mcap")

#: CPU seconds one command may take on one mutated log (the base logs take milliseconds:
#: a command over this is a hang in the field)
BUDGET = 10.0

_parser: argparse.ArgumentParser | None = None
_parsed: dict[tuple[str, ...], argparse.Namespace] = {}


class OverBudget(BaseException):
    """A command ran past its CPU budget (a ``BaseException``: no ``except Exception``
    of the code under test swallows it)."""


@dataclass(slots=True)
class Escape:
    """An exception that escaped a command: the command line and the formatted traceback."""

    argv: list[str]
    kind: str
    where: str  # the innermost mbmon frame, file:line
    text: str


def parse(argv: list[str]) -> argparse.Namespace:
    """The namespace mbmon's own parser (``mbmon.cli.build_parser``) gives ``argv``; each
    command line is parsed once, and every call gets its own copy (a command may change
    its namespace)."""
    global _parser
    key = tuple(argv)
    args = _parsed.get(key)
    if args is None:
        if _parser is None:
            from mbmon.cli import build_parser

            _parser = build_parser()
        args = _parsed[key] = _parser.parse_args(argv)
    return argparse.Namespace(
        **{k: list(v) if isinstance(v, list) else v for k, v in vars(args).items()}
    )  # a tenth of deepcopy's time; options are strings, numbers and lists of them


@contextlib.contextmanager
def cpu_budget(seconds: float | None) -> Iterator[None]:
    """Raise :class:`OverBudget` in the block once the process has used ``seconds`` of CPU
    in it (``ITIMER_PROF``; only in the main thread, where signals arrive)."""
    if not seconds or threading.current_thread() is not threading.main_thread():
        yield
        return

    def over(_signum: int, _frame: object) -> None:
        raise OverBudget(f"over the budget of {seconds} CPU seconds")

    old = signal.signal(signal.SIGPROF, over)
    signal.setitimer(signal.ITIMER_PROF, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, old)


def serve_image(args: argparse.Namespace) -> int:
    """What ``replay LOG --serve`` does before it listens (and ``--to`` before it sends):
    the log opened, its requests and answers decoded again (:mod:`mbmon.io.exchanges`)
    and learnt as the emulated server's register image, with the report of what it
    cannot answer. A damaged log is a message and status 1, as in the command."""
    from mbmon.io.emulate import RegisterImage
    from mbmon.io.exchanges import recorded_exchanges
    from mbmon.io.mcap.reader import LogError, McapLog

    try:
        log = McapLog(args.log)
    except LogError as exc:
        print(f"mbmon: {exc}", file=sys.stderr)
        return 1
    with log:
        try:
            image = RegisterImage.from_exchanges(
                recorded_exchanges(log), miss_exception=2, state="follow"
            )
        except LogError as exc:
            print(f"mbmon: {exc}", file=sys.stderr)
            return 1
        print(image.units, image.answered, image.miss_report())
    return 0


def _escape(argv: list[str], exc: BaseException) -> Escape:
    tb = traceback.extract_tb(exc.__traceback__)
    ours = [f for f in tb if "/mbmon/" in f.filename]
    where = f"{ours[-1].filename.split('/mbmon/', 1)[1]}:{ours[-1].lineno}" if ours else "?"
    kind = "over budget" if isinstance(exc, OverBudget) else type(exc).__name__
    return Escape(argv, kind, where, "".join(traceback.format_exception(exc)))


def run_command(
    argv: list[str], budget: float | None = BUDGET
) -> tuple[int | None, str, str, Escape | None]:
    """Run one log command in-process, as ``mbmon.cli.main`` runs it after parsing, with
    stdout and stderr captured: (exit status, stdout, stderr, what escaped or ``None``).
    A ``SystemExit`` is an exit status (its message on stderr); any other exception, and
    a run past ``budget`` CPU seconds, escaped."""
    args = (
        parse(argv) if argv[0] != "exchanges" else argparse.Namespace(func=serve_image, log=argv[1])
    )
    out, err = io.StringIO(), io.StringIO()
    status: int | None = None
    escape = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            with cpu_budget(budget):
                status = args.func(args)
        except SystemExit as exc:
            if exc.code is None or isinstance(exc.code, int):
                status = exc.code or 0
            else:
                print(exc.code, file=sys.stderr)
                status = 1
        except (Exception, OverBudget) as exc:
            escape = _escape(argv, exc)
    return status, out.getvalue(), err.getvalue(), escape


def run_commands(
    path: Path,
    out_dir: Path,
    turn: int = 0,
    commands: tuple[tuple[str, ...], ...] = COMMANDS,
    budget: float | None = BUDGET,
) -> list[Escape]:
    """Every command of ``commands`` on the log at ``path``; what escaped them.

    Besides escapes, a status other than 0 and 1, and a status of 1 that does not say
    why on stderr, are findings."""
    escapes = []
    for command in commands:
        suffix = EXPORT_SUFFIXES[turn % len(EXPORT_SUFFIXES)]
        argv = [
            str(path) if a == "LOG" else str(out_dir / f"out{suffix}") if a == "OUT" else a
            for a in command
        ]
        status, _out, err, escape = run_command(argv, budget)
        if escape is None and status not in (0, 1):
            escape = Escape(argv, f"status {status}", "?", err)
        elif escape is None and status == 1 and not err.strip():
            escape = Escape(argv, "silent failure", "?", "exit status 1 without a message")
        if escape is not None:
            escapes.append(escape)
    return escapes


# --------------------------------------------------------------------------- campaign


def log_rng(seed: int, i: int) -> random.Random:
    """The generator of log ``i`` of the campaign of ``seed``: any log is made again
    from its two numbers (``--only I``)."""
    return random.Random(seed * 10_000_019 + i)


@dataclass(slots=True)
class Tally:
    """What a campaign did so far: logs by kind, command runs, CPU, findings by place."""

    seed: int
    per_log: int = len(COMMANDS)
    items: int | None = None  # packets of each capture in the base logs (None: all)
    logs: dict[str, int] = field(default_factory=lambda: {"blind": 0, "structured": 0})
    failed: dict[str, int] = field(default_factory=lambda: {"blind": 0, "structured": 0})
    runs: int = 0
    cpu_seconds: float = 0.0
    slowest_log: tuple[float, int] = (0.0, -1)  # CPU seconds, log number
    places: dict[str, list[int]] = field(default_factory=dict)  # place -> [count, first log]

    def line(self) -> str:
        n = sum(self.logs.values())
        return (
            f"seed {self.seed}: {n} logs ({self.logs['blind']} blind, "
            f"{self.logs['structured']} structured), {self.runs} command runs, "
            f"{self.cpu_seconds:.0f} CPU s ({n / max(self.cpu_seconds, 1e-9):.0f} logs/CPU s); "
            f"logs with a finding: blind {self.failed['blind']}, structured "
            f"{self.failed['structured']}; {len(self.places)} places; slowest log "
            f"{self.slowest_log[0] * 1000:.0f} ms (#{self.slowest_log[1]})"
        )

    def as_json(self) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "logs": self.logs,
            "logs_with_a_finding": self.failed,
            "command_runs": self.runs,
            "per_log": self.per_log,
            "base_items": self.items,
            "cpu_seconds": round(self.cpu_seconds, 1),
            "slowest_log_ms": round(self.slowest_log[0] * 1000, 1),
            "slowest_log": self.slowest_log[1],
            "commands": [" ".join(c) for c in COMMANDS],
            "export_suffixes": list(EXPORT_SUFFIXES),
            "findings": {k: {"count": c, "first_log": i} for k, (c, i) in self.places.items()},
        }


def campaign(
    n: int,
    seed: int,
    work: Path,
    report_every: int = 10_000,
    start: int = 0,
    budget: float | None = BUDGET,
    per_log: int = len(COMMANDS),
    bases: list[BaseLog] | None = None,
    items: int | None = None,
) -> Tally:
    """Run commands of :data:`COMMANDS` on mutated logs ``start`` .. ``start + n - 1`` of
    ``seed`` in-process (logs written to ``work``: put it on a tmpfs): ``per_log`` of them
    on each log, taken in turn (with 1, log ``i`` runs command ``i % 8``; with 8, every
    log runs all); count logs, runs and findings by place; keep each place's first log
    and traceback in ``work/found``; ``work/tally.json`` holds the counts at every
    report. ``bases``: the base logs, when the caller recorded them already; else
    recorded here, of the first ``items`` packets of each capture (all: ``None``)."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "found").mkdir(exist_ok=True)
    bases = bases or record_base_logs(work, items=items)
    tally = Tally(seed, per_log, items)
    path = work / "m.mcap"
    for i in range(start, start + n):
        t0 = time.process_time()
        kind, data = mutated(bases, log_rng(seed, i))
        path.write_bytes(data)
        tally.logs[kind] += 1
        commands = tuple(COMMANDS[(i * per_log + j) % len(COMMANDS)] for j in range(per_log))
        escapes = run_commands(path, work, i // len(COMMANDS), commands, budget)
        tally.runs += per_log
        took = time.process_time() - t0
        tally.cpu_seconds += took
        tally.slowest_log = max(tally.slowest_log, (took, i))
        if escapes:
            tally.failed[kind] += 1
        for e in escapes:
            key = f"{e.kind} at {e.where} ({' '.join(e.argv[:1] + e.argv[2:])})"
            if key not in tally.places:
                stem = work / "found" / f"{len(tally.places):03d}"
                stem.with_suffix(".mcap").write_bytes(data)
                stem.with_suffix(".txt").write_text(
                    f"seed {seed} log {i}\n{' '.join(e.argv)}\n{e.text}"
                )
                tally.places[key] = [0, i]
            tally.places[key][0] += 1
        done = i + 1 - start
        if done % report_every == 0 or done == n:
            print(tally.line(), flush=True)
            (work / "tally.json").write_text(json.dumps(tally.as_json(), indent=1))
    return tally


def main() -> None:
    parser = argparse.ArgumentParser(description="the offline campaign of hostile logs")
    parser.add_argument("--logs", type=int, default=10_000, help="how many mutated logs")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--start", type=int, default=0, help="number of the first log")
    parser.add_argument("--only", type=int, help="make log ONLY again, run it, print findings")
    parser.add_argument("--work", type=Path, default=Path("/dev/shm/logmutate"))
    parser.add_argument("--budget", type=float, default=BUDGET, help="CPU s per command")
    parser.add_argument("--report-every", type=int, default=1000)
    parser.add_argument(
        "--items", type=int, help="base logs of the first ITEMS packets of each capture"
    )
    parser.add_argument(
        "--per-log",
        type=int,
        default=len(COMMANDS),
        choices=range(1, len(COMMANDS) + 1),
        metavar="K",
        help=f"commands run on each log, taken in turn (default: all {len(COMMANDS)})",
    )
    args = parser.parse_args()
    work = args.work / f"seed{args.seed}"
    if args.only is not None:
        work.mkdir(parents=True, exist_ok=True)
        kind, data = mutated(
            record_base_logs(work, items=args.items), log_rng(args.seed, args.only)
        )
        (work / "only.mcap").write_bytes(data)
        escapes = run_commands(work / "only.mcap", work, args.only, budget=args.budget)
        print(f"{kind} log {args.only} of seed {args.seed}: {work / 'only.mcap'}")
        for e in escapes:
            print(" ".join(e.argv), e.text, sep="\n")
        raise SystemExit(1 if escapes else 0)
    tally = campaign(
        args.logs,
        args.seed,
        work,
        args.report_every,
        args.start,
        args.budget,
        args.per_log,
        items=args.items,
    )
    print(json.dumps(tally.as_json(), indent=1))


if __name__ == "__main__":
    main()
