"""Every log format reads alike: a log of format 1, 2 or 3 (written before the next
format, kept in tests/io/data/format1/, format2/ and format3/, see their READMEs) and a
log of format 4 written now from the same capture give the same output to every reader:
``replay`` (text, ``--json``, a ``--where``), ``replay --redecode``, ``info --json``
(the message count of ``/modbus/raw`` aside), ``export`` to every suffix; and all print
what ``read`` prints. An unfinished log (cut as SIGKILL leaves it) of any format
replays what it recovered; every message of the old logs still validates against the
schemas stored with it and passes the readers' checks; every protobuf message of a
format-4 log decodes (by mbmon's decoder, and by google.protobuf from the log's own
FileDescriptorSet, the marker of a left-out chunk included) to the object format 2
stored for the same record; the chunks a format-4 log gives its readers are those of
the format-3 log of the same capture."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jsonschema
import logmutate
import pytest
from format4 import as_format3, left_out

from mbmon.io.mcap.layout import LOG_FORMAT, METADATA_NAME
from mbmon.io.mcap.payloads import payload_problem
from mbmon.io.mcap.reader import McapLog

REPO = Path(__file__).resolve().parents[2]
DATA = Path(__file__).resolve().parent / "data"
FORMAT1 = DATA / "format1"
FORMAT2 = DATA / "format2"
FORMAT3 = DATA / "format3"

#: fixture name -> the read options it was recorded with (data/format1/README.md)
LOGS = {
    "demo": [],
    "hrss_ptp": ["--profile", "hrss", "--robot", "192.168.0.10"],
    "sim_rtu": [],
}


def run(argv: list[str]) -> str:
    """One command in-process (mbmon's parser and run functions); its stdout. It must
    exit 0 and let nothing escape."""
    status, out, err, escape = logmutate.run_command(argv, budget=None)
    assert escape is None, escape.text
    assert status == 0, (argv, err)
    return out


def _pair(name: str, folder: Path, tmp_path: Path) -> tuple[str, Path, Path]:
    """(name, its log in ``folder``, a format-4 log written now from the same capture)."""
    capture = REPO / "captures" / f"{name}.pcap"
    old = folder / f"{name}.mcap"
    if not capture.exists() or not old.exists():
        pytest.skip(f"{capture.name} or its {folder.name} log absent")
    copy = tmp_path / f"{name}.pcap"  # the recording's source name, as in the fixture
    shutil.copy(capture, copy)
    new = tmp_path / f"{name}.mcap"
    run(["read", str(copy), *LOGS[name], "-q", "-w", str(new)])
    return name, old, new


@pytest.fixture(
    params=[(n, f) for f in (FORMAT1, FORMAT2, FORMAT3) for n in LOGS],
    ids=lambda p: f"{p[1].name}-{p[0]}",
)
def pair(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[str, Path, Path]:
    """(name, its format-1, 2 or 3 log, a format-4 log written now from the same
    capture)."""
    return _pair(*request.param, tmp_path)


@pytest.fixture(params=list(LOGS))
def pair2(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[str, Path, Path]:
    """(name, its format-2 log, a format-4 log written now from the same capture)."""
    return _pair(request.param, FORMAT2, tmp_path)


@pytest.fixture(params=list(LOGS))
def pair3(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[str, Path, Path]:
    """(name, its format-3 log, a format-4 log written now from the same capture)."""
    return _pair(request.param, FORMAT3, tmp_path)


def test_the_format_is_in_the_metadata(pair: tuple[str, Path, Path]) -> None:
    _, old, new = pair
    with McapLog(old) as log:
        if old.parent == FORMAT1:
            assert "format" not in log.metadata[METADATA_NAME]
        else:
            assert log.metadata[METADATA_NAME]["format"] == old.parent.name[-1]
    with McapLog(new) as log:
        assert log.metadata[METADATA_NAME]["format"] == str(LOG_FORMAT) == "4"


def test_format_2_is_smaller_in_what_it_stores() -> None:
    """Format 2's frames lack the line and null members; its raw chunks their null keys."""
    for name in LOGS:
        with McapLog(FORMAT1 / f"{name}.mcap") as a, McapLog(FORMAT2 / f"{name}.mcap") as b:
            frames = [json.loads(m.raw) for m in b.messages(["/modbus/frames"])]
            old_frames = [json.loads(m.raw) for m in a.messages(["/modbus/frames"])]
            chunks = [json.loads(m.raw) for m in b.messages(["/modbus/raw"])]
        assert frames and all("line" not in f and None not in f.values() for f in frames)
        assert all("line" in f for f in old_frames)
        assert all("event" not in c for c in chunks if c["type"] == "chunk")


def _oracle_classes(log: McapLog) -> dict[str, object]:
    """google.protobuf's message classes built from the log's own schema records."""
    pytest.importorskip("google.protobuf", reason="protobuf (a test extra) not installed")
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    classes: dict[str, object] = {}
    for topic in ("/modbus/frames", "/modbus/raw"):
        stored = log.schema_of(topic)
        assert stored is not None and stored[1] == "protobuf"
        pool = descriptor_pool.DescriptorPool()
        for f in descriptor_pb2.FileDescriptorSet.FromString(stored[2]).file:
            pool.Add(f)
        classes[topic] = message_factory.GetMessageClass(pool.FindMessageTypeByName(stored[0]))
    return classes


def test_format_4_messages_are_format_2_objects(pair2: tuple[str, Path, Path]) -> None:
    """Every /modbus/frames and /modbus/raw message of a format-4 log is protobuf and,
    with the left-out chunks rebuilt from their frames and the marker taken off,
    decodes to the object format 2 stored for the same record (the format-2 fixture,
    message for message); google.protobuf reads every one of them (the marker too),
    with the same field values as mbmon's decoder."""
    from mbmon.io.mcap import proto

    _, old, new = pair2
    topics = ["/modbus/frames", "/modbus/raw"]
    with McapLog(old) as a, McapLog(new) as b:
        stored = [(m.topic, json.loads(m.raw)) for m in a.messages(topics)]
        raws = [(m.topic, m.raw) for m in b.messages(topics)]
        schemas = {t: b.schema_of(t) for t in topics}
    as3 = as_format3([(t, 0, raw) for t, raw in raws])
    decoded = [(t, proto.DECODERS[proto.PROTO_NAMES[t]](raw)) for t, _, raw in as3]
    assert (len(as3) > len(raws)) is ("rtu" not in old.name)  # chunks were left out
    assert decoded == stored
    assert [list(o) for _, o in decoded] == [list(o) for _, o in stored]  # member order
    assert all(s is not None and s[1] == "protobuf" for s in schemas.values())
    with McapLog(new) as b:
        oracle = _oracle_classes(b)  # skips here without google.protobuf (a test extra)
    marked = 0
    for topic, raw in raws:
        theirs = oracle[topic].FromString(raw)  # type: ignore[attr-defined]
        fields = proto.messages()[proto.PROTO_NAMES[topic]]
        ours = proto._decode(fields, raw)
        got = {f.name: (list(v) if f.is_repeated else v) for f, v in theirs.ListFields()}
        assert got == ours
        marked += "chunk" in got
    assert marked == len(as3) - len(raws)  # google.protobuf reads every marker


@pytest.mark.parametrize(
    "args",
    [
        [],
        ["--json"],
        ["--redecode"],
        ["--json", "--redecode"],
        ["--where", "fc 3 or fc 4 or exception"],
    ],
    ids=["text", "json", "redecode", "json-redecode", "where"],
)
def test_replay_prints_the_same_from_both_formats(
    pair: tuple[str, Path, Path], args: list[str]
) -> None:
    _, old, new = pair
    a = run(["replay", str(old), *args])
    assert a.strip()
    assert run(["replay", str(new), *args]) == a


def test_both_formats_replay_what_read_printed(pair: tuple[str, Path, Path]) -> None:
    name, old, new = pair
    capture = new.with_suffix(".pcap")
    for extra in ([], ["--json"]):
        printed = run(["read", str(capture), *LOGS[name], *extra])
        assert run(["replay", str(old), *extra]) == printed
        assert run(["replay", str(new), *extra]) == printed


def test_info_says_the_same_of_both_formats(pair: tuple[str, Path, Path]) -> None:
    """The same, but for the messages format 4 leaves out: the count of /modbus/raw
    messages (and so of all messages) is what the log holds, smaller by one a chunk
    left out; the streams' chunks and bytes and the writer's stats count every chunk."""
    _, old, new = pair
    a, b = (json.loads(run(["info", str(p), "--json"])) for p in (old, new))
    for key in ("file", "size", "command_line", "source"):  # the file and how it was made
        a.pop(key), b.pop(key)
    with McapLog(new) as log:
        fewer = left_out([(m.topic, m.log_time, m.raw) for m in log.messages()])
    assert (fewer > 0) is ("rtu" not in new.name)  # a serial bus's chunks are no MBAP ADUs
    assert b["topics"]["/modbus/raw"] == a["topics"]["/modbus/raw"] - fewer
    assert b["recovered_messages"] == a["recovered_messages"] - fewer
    assert b["status"] == a["status"].replace(
        f"{a['recovered_messages']} messages", f"{b['recovered_messages']} messages"
    )
    for key in ("topics", "recovered_messages", "status"):
        a.pop(key), b.pop(key)
    assert a == b
    assert a["finished"] and not a["damaged_messages"]


@pytest.mark.parametrize("suffix", [".jsonl", ".csv", ".txt", ".pcap", ".pcapng"])
def test_export_writes_the_same_from_both_formats(
    pair: tuple[str, Path, Path], tmp_path: Path, suffix: str
) -> None:
    _, old, new = pair
    outs = []
    for log in (old, new):
        out = tmp_path / f"{log.parent.name}-out{suffix}"
        run(["export", str(log), "-o", str(out)])
        outs.append(out.read_bytes())
    assert outs[0] and outs[0] == outs[1]


def test_export_to_mcap_keeps_the_format(pair: tuple[str, Path, Path], tmp_path: Path) -> None:
    """``export -o x.mcap`` copies the messages as stored: a format-1 log stays format 1
    (no format key) and reads as before, a format-2 log stays format 2."""
    _, old, new = pair
    for log in (old, new):
        out = tmp_path / f"copy-{log.parent.name}.mcap"
        run(["export", str(log), "-o", str(out)])
        with McapLog(log) as a, McapLog(out) as b:
            assert b.metadata[METADATA_NAME].get("format") == a.metadata[METADATA_NAME].get(
                "format"
            )
        assert run(["replay", str(out), "--json"]) == run(["replay", str(log), "--json"])


def _cut_before_summary(path: Path, to: Path) -> Path:
    """The log as a SIGKILL leaves it: its data section without summary and footer."""
    with McapLog(path) as log:
        data_end = max(span.offset + span.length for span in log._layout.chunks)
    to.write_bytes(path.read_bytes()[:data_end])
    return to


def test_unfinished_logs_of_both_formats_replay_alike(
    pair: tuple[str, Path, Path], tmp_path: Path
) -> None:
    _, old, new = pair
    outs = []
    for log in (old, new):
        cut = _cut_before_summary(log, tmp_path / f"cut-{log.parent.name}.mcap")
        with McapLog(cut) as read_back:
            assert not read_back.finished
        outs.append(run(["replay", str(cut), "--json"]))
    assert outs[0] == outs[1] == run(["replay", str(old), "--json"])


def test_old_messages_still_validate(pair: tuple[str, Path, Path]) -> None:
    """Every message of a format-1, 2 or 3 log against the schema stored with it
    (the v1 and v2 files, still in mbmon/schemas; format 3's protobuf messages decoded
    by today's reader) and the readers' checks."""
    _, old, _ = pair
    from mcap.reader import make_reader

    from mbmon.io.mcap.proto import decode_payload

    with open(old, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        validators: dict[str, jsonschema.protocols.Validator] = {}
        for schema, channel, msg in reader.iter_messages():
            assert schema is not None
            if channel.message_encoding == "protobuf":  # format 3 (no field 21 in it)
                obj = decode_payload(schema.name, "protobuf", msg.data)
                assert "chunk" not in obj
                assert payload_problem(channel.topic, obj) is None
                continue
            if schema.name not in validators:
                stored = json.loads(schema.data)
                cls = jsonschema.validators.validator_for(stored)
                validators[schema.name] = cls(stored)
            data = json.loads(msg.data)
            validators[schema.name].validate(data)
            assert payload_problem(channel.topic, data) is None
    if old.parent == FORMAT3:
        assert "foxglove.Log" in validators
        return
    version = "v1" if old.parent == FORMAT1 else "v2"
    assert {f"modbus.Frame.{version}", f"modbus.Raw.{version}", "foxglove.Log"} <= set(validators)


@pytest.mark.parametrize("name", list(LOGS))
def test_format_4_gives_its_readers_the_chunks_of_format_3(name: str, tmp_path: Path) -> None:
    """The chunks and source events ``raw_items`` yields (``--redecode``, export to pcap,
    ``--serve``/``--to``) from a format-4 log are those of the format-3 log of the same
    capture, item for item, the left-out chunks rebuilt where their frames are."""
    from mbmon.io.replay import raw_items

    _, old, new = _pair(name, FORMAT3, tmp_path)
    with McapLog(old) as a, McapLog(new) as b:
        want, got = list(raw_items(a)), list(raw_items(b))
        assert not a.status.skipped and not b.status.skipped
        fewer = left_out([(m.topic, m.log_time, m.raw) for m in b.messages()])
        raw_messages = sum(1 for _ in b.messages(["/modbus/raw"]))
    assert got == want
    assert raw_messages == len(want) - fewer
    if name != "sim_rtu":  # a serial bus: its chunks are no MBAP ADUs, none left out
        assert fewer > len(want) // 2
    else:
        assert fewer == 0


#: the public captures: ../shared from the repository's root (a worktree one level deeper
#: looks one further up), as tests/core/core_diff.py finds them
REAL = next(
    (
        base / "shared" / "captures" / "real"
        for base in (REPO.parent, REPO.parent.parent)
        if (base / "shared" / "captures" / "real").is_dir()
    ),
    REPO.parent / "shared" / "captures" / "real",
)


def _capture_files() -> list[Path]:
    own = sorted((REPO / "captures").glob("*.pcap*"))
    return own + (sorted(REAL.glob("*.pcap*")) if REAL.is_dir() else [])


@pytest.mark.parametrize("path", _capture_files(), ids=lambda p: p.name)
def test_format_4_logs_give_back_every_captured_chunk(path: Path, tmp_path: Path) -> None:
    """On every capture of captures/ and ../shared/captures/real/ (TCP, Modbus/UDP, RTU over
    TCP, noise, holes): the chunks ``raw_items`` yields from the format-4 log ``read -w``
    writes are the chunks the capture gave the pipeline, item for item, as a format-3
    log stores them all."""
    from mbmon.io.replay import raw_items
    from mbmon.model import Chunk
    from mbmon.sources.pcapfile import CaptureError, read_capture

    log = tmp_path / "x.mcap"
    status, _, err, escape = logmutate.run_command(
        ["read", str(path), "-q", "-w", str(log)], budget=None
    )
    assert escape is None, escape.text
    assert status == 0, err
    try:
        want = [c for c in read_capture(path) if isinstance(c, Chunk)]
    except CaptureError:
        pytest.skip(f"{path.name} is no capture mbmon reads ({err.strip()})")
    with McapLog(log) as mlog:
        got = [c for c in raw_items(mlog) if isinstance(c, Chunk)]
        assert not mlog.status.skipped
    assert got == want
