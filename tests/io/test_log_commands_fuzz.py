"""Hostile logs through the log commands: ``replay`` (stored, ``--json``, ``--redecode``,
with ``--since``), ``info`` (text and ``--json``), ``export`` (every format) and what
``replay --serve`` / ``--to`` do with a log before they open a socket.

Two kinds of mutated logs (tests/io/logmutate.py, shared with the offline
campaign): blind byte damage of real zstd-compressed logs (finished, and cut as
``kill -9`` leaves them), and structure-aware damage of logs rewritten with
uncompressed, CRC-less chunks whose JSON payloads, metadata and attachments
get wrong types, integers beyond 64 bits, missing keys, nested garbage and
deep nesting. Whatever the damage, every command ends in an exit status with
no exception escaping it, and a status of 1 comes with a message on stderr.
The byte tables below pin the cases the field found: a damaged first chunk of
an unfinished log, an integer beyond 64 bits under ``--json``, a payload
nested deeper than a parser recurses, and a damaged message in the middle of
a log (reported with where it is, the rest shown).
"""

from __future__ import annotations

import dataclasses
import io
import json
import random
from pathlib import Path

import logmutate
import pytest
from format4 import as_format3
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

SETTINGS = settings(
    max_examples=500,  # of each kind, every command on each: about 20 s on an idle CI machine
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@pytest.fixture(scope="module")
def bases(tmp_path_factory: pytest.TempPathFactory) -> list[logmutate.BaseLog]:
    bases = logmutate.record_base_logs(tmp_path_factory.mktemp("bases"))
    assert bases, "the project's own captures make the base logs"
    return bases


@pytest.fixture(scope="module")
def short_bases(tmp_path_factory: pytest.TempPathFactory) -> list[logmutate.BaseLog]:
    """The base logs of the first 24 packets of each capture (every topic still there),
    as the campaign's ``--items 24`` records them: twice the logs in the same CI time."""
    bases = logmutate.record_base_logs(tmp_path_factory.mktemp("short"), items=24)
    assert bases, "the project's own captures make the base logs"
    return bases


def _no_escape(data: bytes, tmp: Path, turn: int) -> None:
    path = tmp / "hostile.mcap"
    path.write_bytes(data)
    escapes = logmutate.run_commands(path, tmp, turn)
    assert not escapes, "\n".join(f"{' '.join(e.argv)}:\n{e.text}" for e in escapes)


@SETTINGS
@given(seed=st.integers(0, 2**64), turn=st.integers(0, 4))
def test_blind_damage_of_zstd_logs(
    tmp_path: Path, short_bases: list[logmutate.BaseLog], seed: int, turn: int
) -> None:
    rng = random.Random(seed)  # a structured log takes hundreds of draws: one seed
    _no_escape(logmutate.blind(rng.choice(short_bases), rng), tmp_path, turn)


@SETTINGS
@given(seed=st.integers(0, 2**64), turn=st.integers(0, 4))
def test_structure_aware_damage(
    tmp_path: Path, short_bases: list[logmutate.BaseLog], seed: int, turn: int
) -> None:
    rng = random.Random(seed)
    _no_escape(logmutate.structured(rng.choice(short_bases), rng), tmp_path, turn)


# --------------------------------------------------------------------------- pinned cases


def _rewritten(
    base: logmutate.BaseLog, change: dict[int, bytes], *, finished: bool = True
) -> bytes:
    """The base log's messages in uncompressed chunks, message ``i`` replaced by
    ``change[i]``; one chunk per 20 messages or so; cut before its summary unless
    ``finished``."""
    from mbmon.io.mcap.writer import McapFileWriter

    buf = io.BytesIO()
    writer = McapFileWriter(buf, chunk_size=2000)
    writer.compression, writer._compress = "", None
    writer.start(library="test")
    for name, data in base.metadata.items():
        writer.add_metadata(name, data)
    for name, media, data, t in base.attachments:
        writer.add_attachment(0, t, name, media, data)
    channels: dict[str, int] = {}
    for i, (topic, log_time, raw) in enumerate(base.messages):
        if topic not in channels:
            channels[topic] = logmutate.register(writer, topic)
        writer.add_message(channels[topic], log_time, change.get(i, raw))
    writer.finish()
    data = buf.getvalue()
    if not finished:
        data = data[: logmutate.summary_start(data)]
    return data


def _index_of(base: logmutate.BaseLog, topic: str, nth: int) -> int:
    return [i for i, m in enumerate(base.messages) if m[0] == topic][nth]


def _write(tmp: Path, data: bytes) -> Path:
    path = tmp / "pinned.mcap"
    path.write_bytes(data)
    return path


def test_unfinished_log_with_a_damaged_first_chunk(
    tmp_path: Path, bases: list[logmutate.BaseLog]
) -> None:
    """kill -9 left no summary, and the first chunk is damaged: replay and export do not
    raise looking for the first record's time; they show every later chunk and name the
    damaged one by its offset."""
    base = bases[0]
    data = bytearray(base.unfinished)
    first_chunk = next(p for p, op, _n in logmutate.walk(bytes(data)) if op == 0x06)
    data[first_chunk + 9 + 40] ^= 0xFF  # inside its compressed records
    path = _write(tmp_path, bytes(data))
    for argv in (["replay", str(path)], ["replay", str(path), "--since", "+0.1s"],
                 ["export", str(path), "-o", str(tmp_path / "out.jsonl")]):  # fmt: skip
        status, out, err, escape = logmutate.run_command(argv)
        assert escape is None, escape.text
        assert status == 1 and f"chunk at byte {first_chunk}" in err, err
    status, out, err, escape = logmutate.run_command(["replay", str(path)])
    assert len(out.splitlines()) > 50  # the chunks after the damaged one
    lines = (tmp_path / "out.jsonl").read_text().splitlines()
    assert len(lines) > 50


def test_integer_beyond_64_bits_and_deep_nesting(
    tmp_path: Path, bases: list[logmutate.BaseLog]
) -> None:
    """A frame whose ``info``-like free field holds 2**70, and a payload nested 100,000
    deep: replay --json prints the first exactly, the second is reported as damage."""
    base = bases[0]
    frame = _index_of(base, "/modbus/frames", 3)
    obj = logmutate.payload_obj("/modbus/frames", base.messages[frame][2])
    obj["fields"] = {"huge": 2**70}
    deep = _index_of(base, "/modbus/frames", 5)
    data = _rewritten(
        base,
        {
            frame: logmutate.payload_bytes("/modbus/frames", obj),
            deep: logmutate.deep_payload("/modbus/frames"),
        },
    )
    path = _write(tmp_path, data)
    status, out, err, escape = logmutate.run_command(["replay", str(path), "--json"])
    assert escape is None, escape.text
    assert '"huge":1180591620717411303424' in out
    assert status == 1 and "nested too deeply" in err and "1 damaged message" in err, err


def test_a_damaged_message_is_reported_where_it_is_and_the_rest_shown(
    tmp_path: Path, bases: list[logmutate.BaseLog]
) -> None:
    base = bases[0]
    good = logmutate.run_command(["replay", str(_write(tmp_path, _rewritten(base, {}))), "--json"])
    assert good[0] == 0 and good[3] is None
    n = len(good[1].splitlines())
    at = _index_of(base, "/modbus/frames", 10)
    obj = logmutate.payload_obj("/modbus/frames", base.messages[at][2])
    obj["fc"] = "three"  # a string where the schema has an integer
    path = _write(tmp_path, _rewritten(base, {at: logmutate.payload_bytes("/modbus/frames", obj)}))
    status, out, err, escape = logmutate.run_command(["replay", str(path), "--json"])
    assert escape is None, escape.text
    assert status == 1
    assert "message on /modbus/frames at byte" in err and "of the chunk at byte" in err, err
    assert "fc is 'three' where the schema has integer or null" in err
    assert len(out.splitlines()) == n - 1  # that record's object only
    status, out, err, escape = logmutate.run_command(["replay", str(path)])
    assert len(out.splitlines()) == n  # its monitor line is intact: shown
    status, out, err, escape = logmutate.run_command(["info", str(path), "--json"])
    assert status == 1 and json.loads(out)["damaged_messages"], err


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("direction", "bus"),  # a chunk of a TCP stream said to be on a serial bus
        ("info", {"how": True}),  # a source event whose info has the wrong types
        ("info", {"how": "fin", "by": 7}),
        ("info", {"bytes": 1e999, "direction": "c2s"}),
        ("info", {"direction": "sideways"}),
        ("event", "timeout"),  # not a source event: the pipeline makes those itself
    ],
)
def test_redecode_of_damaged_raw_messages(
    tmp_path: Path, bases: list[logmutate.BaseLog], field: str, value: object
) -> None:
    """Found by the offline campaign: raw messages whose fields have the right JSON types
    but values the decoder cannot take. ``replay --redecode`` and ``export -o .pcap``
    leave such a message out, say where it is, and decode everything else."""
    base = next(b for b in bases if b.name == "hrss_ptp")
    # every chunk's raw message back (format 3's form: format 4 left them out)
    base = dataclasses.replace(base, messages=as_format3(base.messages))
    raw = [i for i, m in enumerate(base.messages) if m[0] == "/modbus/raw"]
    want = "chunk" if field == "direction" else "event"
    at = next(
        i for i in raw if logmutate.payload_obj("/modbus/raw", base.messages[i][2])["type"] == want
    )
    obj = logmutate.payload_obj("/modbus/raw", base.messages[at][2])
    obj[field] = value
    if field == "info":
        obj["event"] = "disconnect" if "how" in value else "gap"  # type: ignore[operator]
    path = _write(tmp_path, _rewritten(base, {at: logmutate.payload_bytes("/modbus/raw", obj)}))
    for argv in (["replay", str(path), "--redecode"],
                 ["export", str(path), "-o", str(tmp_path / "x.pcap")]):  # fmt: skip
        status, out, err, escape = logmutate.run_command(argv)
        assert escape is None, escape.text
        assert status == 1 and "1 damaged message left out" in err, err
        assert "message on /modbus/raw at byte" in err
    status, out, err, escape = logmutate.run_command(["replay", str(path), "--redecode"])
    assert len(out.splitlines()) > 50  # the whole session but what the message held


# --------------------------------------------------------------------------- the harness


def test_base_logs_are_finished_and_cut(tmp_path: Path, bases: list[logmutate.BaseLog]) -> None:
    """The unfinished base logs are the finished ones cut where their summary starts
    (the footer's first field): a reader sees no footer and recovers every message.
    (The footer was once read 9 bytes off and every 'unfinished' log was whole.)"""
    from mbmon.io.mcap.reader import McapLog

    for base in bases:
        assert len(base.unfinished) < len(base.finished), base.name
        assert base.finished.startswith(base.unfinished)
        with McapLog(_write(tmp_path, base.unfinished)) as log:
            assert not log.finished
            assert [(m.topic, m.log_time, m.raw) for m in log.messages()] == base.messages
            assert log.status.messages == len(base.messages)


def test_the_harness_reports_a_planted_fault_with_its_place(
    tmp_path: Path, bases: list[logmutate.BaseLog], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A detector that cannot fail proves nothing: with a fault planted in the reader
    (a ``KeyError`` from the record parser, as a missed check would raise), every
    command that reads messages reports it as an escape naming the reader's line;
    the campaign counts the logs and keeps one."""
    from mbmon.io.mcap.reader import McapLog

    def broken(self: McapLog, data: bytes, chunk_offset: int, layout: object = None) -> None:
        raise KeyError("planted")

    path = _write(tmp_path, bases[0].finished)
    assert not logmutate.run_commands(path, tmp_path)  # the log itself is fine
    monkeypatch.setattr(McapLog, "_parse_records", broken)
    escapes = logmutate.run_commands(path, tmp_path)
    assert len(escapes) == len(logmutate.COMMANDS)
    assert {e.kind for e in escapes} == {"KeyError"}
    assert all(e.where.startswith("tests/") or "reader" in e.text for e in escapes)
    tally = logmutate.campaign(3, 1, tmp_path / "campaign", report_every=10, bases=bases)
    assert sum(tally.logs.values()) == 3 and tally.runs == 3 * len(logmutate.COMMANDS)
    # every structured log reaches the parser (its chunks are uncompressed and whole)
    assert tally.failed["structured"] == tally.logs["structured"] >= 1
    assert any(k.startswith("KeyError at ") for k in tally.places)
    assert (tmp_path / "campaign" / "found" / "000.mcap").exists()
    tally_json = json.loads((tmp_path / "campaign" / "tally.json").read_text())
    assert tally_json["logs"] == tally.logs and tally_json["findings"]


def test_the_harness_stops_a_command_over_its_budget(
    tmp_path: Path, bases: list[logmutate.BaseLog], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A reader that never ends (a loop over a length that does not advance) is a
    finding too: the CPU budget stops the command and reports it, and the next
    command runs."""
    from mbmon.io.mcap.reader import McapLog

    def spins(self: McapLog, data: bytes, chunk_offset: int, layout: object = None) -> None:
        while True:
            pass

    path = _write(tmp_path, bases[0].finished)
    monkeypatch.setattr(McapLog, "_parse_records", spins)
    status, _out, _err, escape = logmutate.run_command(["replay", str(path)], budget=0.3)
    assert escape is not None and escape.kind == "over budget", escape
    monkeypatch.undo()
    status, out, _err, escape = logmutate.run_command(["replay", str(path)], budget=0.3)
    assert escape is None and status == 0 and out


def test_a_system_exit_is_an_exit_status(tmp_path: Path) -> None:
    """What ``main`` would end with: a ``SystemExit`` (here argparse's, for a missing
    file is not one; a log that is not MCAP is a message and status 1) is a status."""
    path = _write(tmp_path, b"not a log at all")
    status, _out, err, escape = logmutate.run_command(["info", str(path)])
    assert escape is None and status == 1 and "not an MCAP file" in err, err
