"""Mutated MCAP logs through the tolerant reader.

Logs written by the sink here are damaged the ways real files get damaged:
every length and offset field of every record (chunk lengths, compressed and
uncompressed sizes, name lengths, index offsets and lengths, the footer's
pointers) set to values that lie (0, tiny, huge, just past the end, off by
one), random bytes, and truncation. Whatever the damage, the reader raises
nothing but its own :class:`LogError`, what it returns is the log's messages
in their order (a damaged chunk left out, the chunks after it read), and every
message of a chunk that ends before the first damaged byte comes back. A
single finished and a single unfinished log go through every length mutation
(a few thousand reads): the 83-in-a-million tracebacks of the field test all
came from length fields, which this hits on every read.
"""

from __future__ import annotations

import random
import struct
from pathlib import Path

import pytest
import sink_records as records
from mcap.reader import make_reader

from mbmon.format import View
from mbmon.io.mcap.reader import LogError, McapLog
from mbmon.sinks.base import SinkContext
from mbmon.sinks.mcap import McapSink

CTX = SinkContext(view=View(), command_line=["mbmon", "read", "x"], source="x")
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")


class Log:
    """A log as bytes with what a mutation needs: messages, chunk ends, field positions."""

    def __init__(self, data: bytes, tmp: Path, finished: bytes | None = None) -> None:
        """``data``, and for a log cut before its summary the ``finished`` log it was cut
        from (the ``mcap`` package reads the reference messages from that one)."""
        self.data = data
        ref = tmp / "ref.mcap"
        ref.write_bytes(finished or data)
        with open(ref, "rb") as f:
            self.messages = [
                (m.log_time, bytes(m.data))
                for _, _, m in make_reader(f, validate_crcs=True).iter_messages(
                    log_time_order=False
                )
            ]
        ref.write_bytes(data)
        self.records = list(walk(data))
        #: (end offset of a chunk, messages in the file up to and including it)
        self.chunk_ends: list[tuple[int, int]] = []
        with McapLog(ref) as log:
            spans = log._layout.chunks
            for span in spans:
                n = len(list(log._parse_records(log._chunk_records(span), span.offset)))
                before = self.chunk_ends[-1][1] if self.chunk_ends else 0
                self.chunk_ends.append((span.offset + span.length, before + n))
        assert self.chunk_ends and self.chunk_ends[-1][1] == len(self.messages)
        self.fields = list(length_fields(data, self.records))

    def guaranteed(self, damage_at: int) -> int:
        """Messages in the chunks that end before the first damaged byte."""
        n = 0
        for end, count in self.chunk_ends:
            if end <= damage_at:
                n = count
        return n


def walk(data: bytes) -> list[tuple[int, int, int]]:
    """Top-level records: (offset, opcode, body length), data section and summary."""
    out = []
    p = 8
    while p + 9 <= len(data) - 8:
        op, length = struct.unpack_from("<BQ", data, p)
        out.append((p, op, length))
        p += 9 + length
    return out


def length_fields(data: bytes, recs: list[tuple[int, int, int]]) -> list[tuple[int, int]]:
    """(position, width) of every length/offset field a reader trusts."""
    fields: list[tuple[int, int]] = []
    for p, op, _length in recs:
        body = p + 9
        fields.append((p + 1, 8))  # every record's own length
        if op == 0x06:  # chunk: uncompressed size, crc, compression name length, records length
            clen = _U32.unpack_from(data, body + 28)[0]
            fields += [(body + 16, 8), (body + 24, 4), (body + 28, 4), (body + 32 + clen, 8)]
        elif op == 0x08:  # chunk index: start offset, length, index map length
            fields += [(body + 16, 8), (body + 24, 8), (body + 32, 4)]
        elif op in (0x0A, 0x0D):  # attachment / metadata index: offset, length
            fields += [(body, 8), (body + 8, 8)]
        elif op == 0x0E:  # summary offset: group start and length
            fields += [(body + 1, 8), (body + 9, 8)]
        elif op == 0x02:  # footer: summary start, summary offset start, crc
            fields += [(body, 8), (body + 8, 8), (body + 16, 4)]
        elif op in (0x03, 0x04, 0x0C, 0x09):  # schema/channel/metadata/attachment: first string
            fields.append((body + (2 if op == 0x03 else 4 if op == 0x04 else 0), 4))
    return fields


def lies(original: int, width: int, size: int, at: int, rng: random.Random) -> list[int]:
    top = (1 << (8 * width)) - 1
    values = {0, 1, 8, 9, 22, top, top >> 1, 1 << 31, size, size - at, size - at + 1}
    values |= {original - 1, original + 1, original * 2, rng.randrange(top), rng.randrange(size)}
    return sorted(v for v in values if 0 <= v <= top and v != original)


def read(path: Path, data: bytes) -> list[tuple[int, bytes]]:
    """Everything the tolerant reader gives back; nothing but LogError may escape it."""
    path.write_bytes(data)
    got: list[tuple[int, bytes]] = []
    try:
        log = McapLog(path)
    except LogError:
        return got
    with log:
        try:
            for m in log.messages():
                got.append((m.log_time, m.raw))
        except LogError as exc:
            assert "byte" in str(exc), f"damage reported without its offset: {exc}"
        log.status.describe()
        if log.status.stopped_at is not None:
            assert 0 <= log.status.stopped_at <= len(data)
    return got


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory, session_stream: list) -> list[Log]:
    """A finished log of many small chunks, and the same log cut before its summary."""
    tmp = tmp_path_factory.mktemp("fuzz")
    path = tmp / "small.mcap"
    with McapSink(path, CTX, chunk_size=300) as sink:
        records.feed(sink, session_stream)
    data = path.read_bytes()
    summary_start = _U64.unpack_from(data, len(data) - 8 - 20)[0]
    return [Log(data, tmp), Log(data[:summary_start], tmp, data)]


def check(log: Log, damaged: bytes, damage_at: int, tmp: Path, what: str) -> None:
    got = read(tmp / "m.mcap", damaged)
    rest = iter(log.messages)  # a damaged chunk is passed over: the rest still comes back
    assert all(m in rest for m in got), f"{what}: not the log's messages in its order"
    need = log.guaranteed(damage_at)
    assert got[:need] == log.messages[:need], f"{what}: messages before the damage lost"


@pytest.mark.parametrize("which", [0, 1], ids=["finished", "unfinished"])
def test_every_length_field_lies(tmp_path: Path, logs: list[Log], which: int) -> None:
    log = logs[which]
    rng = random.Random(which)
    size = len(log.data)
    tried = 0
    for at, width in log.fields:
        if at + width > size:
            continue
        fmt = _U64 if width == 8 else _U32
        original = fmt.unpack_from(log.data, at)[0]
        for value in lies(original, width, size, at, rng):
            damaged = bytearray(log.data)
            fmt.pack_into(damaged, at, value)
            check(log, bytes(damaged), at, tmp_path, f"{width}-byte field at {at} = {value}")
            tried += 1
    assert tried > 500


@pytest.mark.parametrize("which", [0, 1], ids=["finished", "unfinished"])
def test_random_bytes_and_truncation(tmp_path: Path, logs: list[Log], which: int) -> None:
    log = logs[which]
    rng = random.Random(100 + which)
    size = len(log.data)
    for n in range(900):
        damaged = bytearray(log.data)
        mode = n % 3
        if mode == 0:  # one random byte
            at = rng.randrange(size)
            damaged[at] = rng.randrange(256)
            first = at
        elif mode == 1:  # a burst of random bytes, and a cut
            at = rng.randrange(size)
            damaged[at : at + 8] = rng.randbytes(8)
            del damaged[rng.randrange(at, size + 1) :]
            first = at
        else:  # a length field set at random, plus a random byte after it
            at, width = rng.choice(log.fields)
            damaged[at : at + width] = rng.randbytes(width)
            if at + width < size:
                damaged[rng.randrange(at + width, size)] = rng.randrange(256)
            first = at
        check(log, bytes(damaged[:size]), first, tmp_path, f"mutation {n} (mode {mode})")
