"""Reading records back: merge by index, raw re-decode, recorded options, filters, pacing."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest
import sink_records as records

from mbmon.format import View, record_line, record_to_json
from mbmon.io.mcap.reader import McapLog
from mbmon.io.replay import (
    FilterError,
    Pacer,
    RecordFilter,
    logged_records,
    parse_fcs,
    parse_range,
    parse_when,
    raw_items,
    recorded_annotator,
    recorded_options,
    touches,
)
from mbmon.model import Chunk, Record
from mbmon.pipeline import Pipeline
from mbmon.sinks.base import SinkContext
from mbmon.sinks.mcap import McapSink

VIEW = View(robot="192.168.0.10")
CTX = SinkContext(
    view=VIEW,
    command_line=["mbmon", "read", "x.pcap", "--robot", "192.168.0.10", "--timeout", "0.25"],
    source="x.pcap",
    timeout=0.25,
)


@pytest.fixture()
def session_log(tmp_path: Path, session_stream: list) -> Path:
    path = tmp_path / "s.mcap"
    with McapSink(path, CTX) as sink:
        records.feed(sink, session_stream)
    return path


def test_logged_records_are_the_records(session_log: Path, session_stream: list) -> None:
    recs = [x for x in session_stream if isinstance(x, Record)]
    with McapLog(session_log) as log:
        got = list(logged_records(log))
    assert [g.index for g in got] == [r.index for r in recs]  # noise stored twice, out once
    assert [g.text for g in got] == [record_line(r, VIEW) for r in recs]
    assert [g.obj for g in got] == [json.loads(json.dumps(record_to_json(r, VIEW))) for r in recs]
    assert [g.time for g in got] == [r.ts for r in recs]
    assert {g.level for g in got} <= {1, 2, 3, 4}


def test_raw_items_redecode_to_the_same_records(session_log: Path, session_stream: list) -> None:
    with McapLog(session_log) as log:
        items = list(raw_items(log))
    chunks = [x for x in session_stream if isinstance(x, Chunk)]
    assert [x for x in items if isinstance(x, Chunk)] == chunks
    again = [r for r in Pipeline().run(items)]
    recs = [x for x in session_stream if isinstance(x, Record)]
    assert [record_to_json(r, VIEW) for r in again] == [record_to_json(r, VIEW) for r in recs]


def test_recorded_options(session_log: Path) -> None:
    with McapLog(session_log) as log:
        opts = recorded_options(log)
        assert recorded_annotator(log, opts) is None
    assert opts.robot == "192.168.0.10" and opts.timeout == 0.25 and opts.profile_specs == []


CELL_TOML = """\
[profile]
name = "cell"

[[holding_registers]]
name = "SPEED"
address = 200
type = "u16"
label = "conveyor speed"
"""


def test_redecode_uses_the_profile_text_stored_in_the_log(tmp_path: Path) -> None:
    """The profile file is gone (or changed) by replay time: the log's copy is used."""
    profile = tmp_path / "cell.toml"
    profile.write_text(CELL_TOML)
    from mbmon.cli import make_annotator

    spec = f"unit:1={profile}"
    items = records.session_items()
    stream = records.run_pipeline(items, make_annotator([spec]))
    ctx = SinkContext(
        view=View(),
        command_line=["mbmon", "read", "x.pcap", "--profile", spec],
        source="x.pcap",
        profiles=[("cell", CELL_TOML)],
        profile_specs=[spec],
    )
    path = tmp_path / "p.mcap"
    with McapSink(path, ctx) as sink:
        records.feed(sink, stream)
    profile.write_text(CELL_TOML.replace("conveyor speed", "SOMETHING ELSE"))
    with McapLog(path) as log:
        opts = recorded_options(log)
        assert opts.profile_specs == [spec]
        annotator = recorded_annotator(log, opts)
        again = list(Pipeline(annotator).run(list(raw_items(log))))
    lines = [record_line(r, View()) for r in again]
    assert lines == [record_line(r, View()) for r in stream if isinstance(r, Record)]
    assert any("conveyor speed" in line or "SPEED" in line for line in lines)
    assert not any("SOMETHING ELSE" in line for line in lines)


def obj(**kw: object) -> dict:
    base = {"unit": 1, "fc": 3, "address": 200, "count": 2, "kind": "request"}
    base.update(kw)
    return base


def test_filters() -> None:
    flt = RecordFilter(units=frozenset({1}), fcs=parse_fcs("3,0x10"), address=parse_range("201"))
    assert flt.matches(obj(), "line", 0.0)
    assert not flt.matches(obj(unit=2), "line", 0.0)
    assert not flt.matches(obj(fc=4), "line", 0.0)
    assert not flt.matches(obj(address=202), "line", 0.0)
    assert not flt.matches({"kind": "event", "unit": None, "fc": None}, "connect", 0.0)
    assert not flt.matches(None, "", 0.0)
    assert RecordFilter().matches(None, "", 0.0)
    assert RecordFilter(grep="ptp").matches(None, "R201 = PTP (0)", 0.0)
    assert not RecordFilter(grep="lin").matches(None, "R201 = PTP (0)", 0.0)
    t = RecordFilter(since=10.0, until=20.0)
    assert [t.matches(None, "", x) for x in (9.99, 10.0, 20.0, 20.01)] == [False, True, True, False]


def test_touches() -> None:
    assert touches(obj(address=200, count=2), 201, 300)
    assert not touches(obj(address=200, count=2), 202, 300)
    assert touches(obj(address=250, count=None), 250, 250)
    fc17 = obj(fc=0x17, address=0, count=1, fields={"write_address": 500, "write_count": 4})
    assert touches(fc17, 503, 503) and not touches(fc17, 504, 600)
    assert not touches({"address": None}, 0, 65535)


def test_parse_helpers_reject_nonsense() -> None:
    for bad in ("", "x", "0x"):
        with pytest.raises(FilterError):
            parse_fcs(bad)
    for bad in ("300-200", "-1", "70000", "a-b"):
        with pytest.raises(FilterError):
            parse_range(bad)
    assert parse_range("0x10-0x20") == (16, 32)


def test_parse_when() -> None:
    start = dt.datetime(2024, 5, 1, 12, 0, 0).timestamp()
    assert parse_when("+5s", start) == start + 5
    assert parse_when("+1m30s", start) == start + 90
    assert parse_when("+250ms", start) == pytest.approx(start + 0.25)
    assert parse_when("+2.5", start) == start + 2.5
    assert parse_when("1h", start) == start + 3600
    assert parse_when("12:00:05", start) == start + 5
    assert parse_when("2024-05-01T12:00:07", start) == start + 7
    assert (
        parse_when("2024-05-01T10:00:00Z", start)
        == dt.datetime(2024, 5, 1, 10, tzinfo=dt.UTC).timestamp()
    )
    assert parse_when("1714560000", start) == 1714560000.0
    for bad in ("+5 parsecs", "yesterday", ""):
        with pytest.raises(FilterError):
            parse_when(bad, start)
    with pytest.raises(FilterError):
        parse_when("+5s", None)


class FakeClock:
    """A monotonic clock whose sleeps always overshoot by ``late`` seconds."""

    def __init__(self, late: float) -> None:
        self.now = 100.0
        self.late = late
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds + self.late


def test_pacer_schedules_from_one_start_without_drift() -> None:
    fake = FakeClock(late=0.004)
    pacer = Pacer(2.0, clock=fake.clock, sleep=fake.sleep)
    times = [1000.0 + 0.1 * k for k in range(200)]  # 20 s of capture
    due = []
    for ts in times:
        pacer.wait(ts)
        due.append(fake.now)
    # every wake-up is at most one oversleep after its due time: no accumulation
    for k, when in enumerate(due):
        target = 100.0 + (times[k] - times[0]) / 2.0
        assert target - 1e-9 <= when <= target + 0.004 + 1e-9
    assert due[-1] - due[0] == pytest.approx(9.95, abs=0.01)  # 19.9 s at 2x
    assert all(s == pytest.approx(0.046) for s in fake.sleeps[1:])  # 0.05 - 0.004 late


def test_pacer_never_sleeps_when_behind() -> None:
    fake = FakeClock(late=0.0)
    pacer = Pacer(1.0, clock=fake.clock, sleep=fake.sleep)
    pacer.wait(0.0)
    fake.now += 10.0  # the consumer stalled
    for ts in (1.0, 2.0, 3.0):
        pacer.wait(ts)
    assert fake.sleeps == []
    with pytest.raises(ValueError):
        Pacer(0)


def test_redecode_binds_each_stored_profile_as_recorded(tmp_path: Path) -> None:
    """Two profile files whose names differ from their file names, bound to two units."""
    from mbmon.cli import make_annotator

    one = tmp_path / "plc.toml"
    two = tmp_path / "gripper.toml"
    one.write_text(CELL_TOML)
    two.write_text(CELL_TOML.replace('"cell"', '"tool"').replace("conveyor speed", "jaw force"))
    specs = [f"unit:1={one}", f"unit:2={two}"]
    items = records.session_items()
    items.insert(
        1,
        records.Chunk(
            records.T0,
            records.TCP,
            records.Direction.C2S,
            records.mbap(9, 2, bytes.fromhex("0600C80005")),
        ),
    )
    stream = records.run_pipeline(items, make_annotator(specs))
    argv = ["mbmon", "read", "x.pcap", "--profile", specs[0], f"--profile={specs[1]}"]
    ctx = SinkContext(
        view=View(),
        command_line=argv,
        source="x.pcap",
        profiles=[("cell", one.read_text()), ("tool", two.read_text())],
        profile_specs=specs,
    )
    path = tmp_path / "two.mcap"
    with McapSink(path, ctx) as sink:
        records.feed(sink, stream)
    one.unlink()
    two.unlink()
    with McapLog(path) as log:
        assert json.loads(log.metadata["mbmon"]["profile_bindings"]) == [
            [specs[0], 0],
            [specs[1], 1],
        ]
        again = list(
            Pipeline(recorded_annotator(log, recorded_options(log))).run(list(raw_items(log)))
        )
    lines = [record_line(r, View()) for r in again]
    assert lines == [record_line(r, View()) for r in stream if isinstance(r, Record)]
    text = "\n".join(lines)
    assert "conveyor speed" in text and "jaw force" in text


# --------------------------------------------------------------------------- analysis settings


def timeout_items() -> list:
    """Two requests 0.5 s apart, the first never answered: a 0.25 s timeout reports it
    while the second arrives, the default 1 s only when the capture ends."""
    c2s = records.Direction.C2S
    return [
        records.Chunk(
            records.T0, records.TCP, c2s, records.mbap(1, 1, bytes.fromhex("0300C80001"))
        ),
        records.Chunk(
            records.T0 + 0.5, records.TCP, c2s, records.mbap(2, 1, bytes.fromhex("0300C90001"))
        ),
        records.Chunk(
            records.T0 + 0.51,
            records.TCP,
            records.Direction.S2C,
            records.mbap(2, 1, bytes.fromhex("0302002A")),
        ),
    ]


def lines_of(recs: list) -> list[str]:
    return [record_line(r, View()) for r in recs if isinstance(r, Record)]


def test_redecode_uses_the_stored_settings_not_the_command_line(tmp_path: Path) -> None:
    """The metadata keys profile_specs, timeout and baud are what the recording was given;
    they win over a command line that says otherwise (a wrapper, an alias, a shell)."""
    profile = tmp_path / "cell.toml"
    profile.write_text(CELL_TOML)
    from mbmon.cli import make_annotator
    from mbmon.pipeline import PipelineConfig

    spec = f"unit:1={profile}"
    items = timeout_items()
    out: list = []
    live = Pipeline(make_annotator([spec]), PipelineConfig(timeout=0.25, baudrate=19200))
    for item in items:
        out.append(item)
        out.extend(live.feed(item))
    out.extend(live.finish())
    ctx = SinkContext(
        view=View(),
        command_line=["mbmon", "read", "x.pcap", "--timeout", "5"],  # not what was in force
        source="x.pcap",
        profiles=[("cell", CELL_TOML)],
        profile_specs=[spec],
        timeout=0.25,
        baud=19200,
    )
    path = tmp_path / "s.mcap"
    with McapSink(path, ctx) as sink:
        records.feed(sink, out)
    with McapLog(path) as log:
        meta = log.metadata["mbmon"]
        assert json.loads(meta["profile_specs"]) == [spec]
        assert (json.loads(meta["timeout"]), json.loads(meta["baud"])) == (0.25, 19200)
        opts = recorded_options(log)
        assert (opts.profile_specs, opts.timeout, opts.baud) == ([spec], 0.25, 19200)
        config = PipelineConfig(timeout=opts.timeout, baudrate=opts.baud)
        again = list(Pipeline(recorded_annotator(log, opts), config).run(list(raw_items(log))))
    assert lines_of(again) == lines_of(out)
    text = "\n".join(lines_of(out))
    assert "SPEED" in text or "conveyor speed" in text
    early = [r for r in again if r.event is not None and r.ts < records.T0 + 0.6]
    assert [r.event.kind.value for r in early] == ["timeout"]  # the 0.25 s timeout, stored


def without_keys(src: Path, dst: Path, keys: set[str]) -> Path:
    """A copy of a log as an older mbmon wrote it: the same records and attachments, its
    metadata without ``keys`` (written with the ``mcap`` package's own writer)."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="", library="mbmon 0.1 (older)")
        schema_ids = {
            sid: writer.register_schema(s.name, s.encoding, s.data)
            for sid, s in summary.schemas.items()
        }
        channel_ids = {
            cid: writer.register_channel(c.topic, c.message_encoding, schema_ids[c.schema_id])
            for cid, c in summary.channels.items()
        }
        for meta in reader.iter_metadata():
            writer.add_metadata(
                meta.name, {k: v for k, v in meta.metadata.items() if k not in keys}
            )
        for att in reader.iter_attachments():
            writer.add_attachment(att.create_time, att.log_time, att.name, att.media_type, att.data)
        for _, channel, msg in reader.iter_messages(log_time_order=False):
            writer.add_message(channel_ids[channel.id], msg.log_time, msg.data, msg.publish_time)
        writer.finish()
    return dst


NEW_KEYS = {"profile_specs", "timeout", "baud"}


def test_older_log_settings_come_from_its_command_line(tmp_path: Path) -> None:
    """A log written before the settings keys: they are parsed from its command line."""
    profile = tmp_path / "cell.toml"
    profile.write_text(CELL_TOML)
    from mbmon.cli import make_annotator
    from mbmon.pipeline import PipelineConfig

    spec = f"unit:1={profile}"
    live = Pipeline(make_annotator([spec]), PipelineConfig(timeout=0.25))
    out: list = []
    for item in timeout_items():
        out.append(item)
        out.extend(live.feed(item))
    out.extend(live.finish())
    argv = ["mbmon", "read", "x.pcap", "--profile", spec, "--timeout", "0.25", "--baud", "9600"]
    ctx = SinkContext(
        view=View(),
        command_line=argv,
        source="x.pcap",
        profiles=[("cell", CELL_TOML)],
        profile_specs=[spec],
        timeout=0.25,
        baud=9600,
    )
    new = tmp_path / "new.mcap"
    with McapSink(new, ctx) as sink:
        records.feed(sink, out)
    old = without_keys(new, tmp_path / "old.mcap", NEW_KEYS)
    with McapLog(old) as log:
        assert NEW_KEYS.isdisjoint(log.metadata["mbmon"])
        opts = recorded_options(log)
        assert (opts.profile_specs, opts.timeout, opts.baud) == ([spec], 0.25, 9600)
        config = PipelineConfig(timeout=opts.timeout, baudrate=opts.baud)
        again = list(Pipeline(recorded_annotator(log, opts), config).run(list(raw_items(log))))
        assert [g.text for g in logged_records(log)] == lines_of(out)
    assert lines_of(again) == lines_of(out)
    # one key missing or damaged: that one from the command line, the others as stored
    partly = without_keys(new, tmp_path / "partly.mcap", {"timeout"})
    with McapLog(partly) as log:
        assert recorded_options(log).timeout == 0.25
    ctx5 = SinkContext(view=View(), command_line=[*argv, "--timeout", "5"], timeout=0.25)
    with McapSink(tmp_path / "five.mcap", ctx5) as sink:
        records.feed(sink, out)
    older = without_keys(tmp_path / "five.mcap", tmp_path / "five-old.mcap", {"timeout"})
    with McapLog(older) as log:
        assert recorded_options(log).timeout == 5.0  # argparse: the last --timeout
    with McapLog(tmp_path / "five.mcap") as log:
        assert recorded_options(log).timeout == 0.25


def test_recorded_options_without_any_settings(tmp_path: Path, session_stream: list) -> None:
    """No keys and no usable command line: the defaults."""
    ctx = SinkContext(view=View(), command_line=[], source="x")
    path = tmp_path / "bare.mcap"
    with McapSink(path, ctx) as sink:
        records.feed(sink, session_stream)
    bare = without_keys(path, tmp_path / "bare-old.mcap", NEW_KEYS)
    with McapLog(bare) as log:
        opts = recorded_options(log)
    assert (opts.profile_specs, opts.timeout, opts.baud) == ([], 1.0, None)


def test_argv_settings_read_a_stored_command_line_like_argparse() -> None:
    """Older logs: the settings come from the stored argv without the CLI's parser."""
    from mbmon.io.replay import argv_settings

    argv = ["read", "x.pcap", "--profile", "hrss", "-w", "--timeout"]  # -w takes the next word
    argv += ["--profile=unit:2=a.toml", "--timeout", "0.25", "--baud=9600", "--json"]
    argv += ["--prof", "xeg", "--", "--baud", "1"]  # an abbreviation; "--" ends the options
    assert argv_settings(argv) == {
        "profile": ["hrss", "unit:2=a.toml", "xeg"], "timeout": 0.25, "baud": 9600
    }  # fmt: skip
    # a value that is not a number is left out, not an error
    assert argv_settings(["read", "--timeout", "soon", "--baud", "-3"]) == {"profile": []}
    assert argv_settings(["read", "-wlog.mcap", "--timeout", "2"])["timeout"] == 2.0
    assert argv_settings([]) == {"profile": []}
