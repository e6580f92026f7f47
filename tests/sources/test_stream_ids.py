"""Several inputs of one run never share a stream id: the hub owns the one allocator
(``Hub.stream_ids``), every source takes its ids there, and each input is decoded as
it is alone. Two captures holding the same TCP 5-tuple (and the same transaction
ids, with different answers), written by the project's own pcap writer, read in
one command: each input's requests pair only with its own answers, and the text,
JSON and MCAP outputs equal reading them one by one but for what one run must
number once (stream ids, record numbers) and the one summary."""

from __future__ import annotations

import io
import json
import re
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mbmon_cli import mbmon

from mbmon.format import View
from mbmon.hub import Hub
from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.pipeline import Pipeline
from mbmon.sinks.console import ConsoleListener
from mbmon.sources.base import run_sources
from mbmon.sources.files import CaptureFileSource, McapLogSource
from mbmon.stream_ids import StreamIds

CLIENT, SERVER = "10.0.0.2:40000", "10.0.0.1:502"
REQUEST = bytes.fromhex("000000060103 0064 0001")  # after the tid: read R100


def write_capture(path: Path, t0: float, values: list[int], *, handshake: bool) -> Path:
    """Requests tid 1.. for R100 answered with ``values``; then a request (tid 9) that
    is never answered and half an ADU: one TCP connection, ``CLIENT`` → ``SERVER``."""
    conv = TcpConversation(CLIENT, SERVER)
    ts = t0
    with PcapWriter(path) as w:
        if handshake:
            for frame in conv.open():
                w.write(ts, frame)
        for tid, value in enumerate(values, 1):
            ts += 0.01
            w.write(ts, conv.send(True, tid.to_bytes(2, "big") + REQUEST))
            ts += 0.002
            answer = bytes.fromhex("00000005010302") + value.to_bytes(2, "big")
            w.write(ts, conv.send(False, tid.to_bytes(2, "big") + answer))
        ts += 0.01
        w.write(ts, conv.send(True, (9).to_bytes(2, "big") + REQUEST))
        ts += 0.3
        w.write(ts, conv.send(True, bytes.fromhex("000A000000060103")))
    return path


@pytest.fixture
def captures(tmp_path: Path) -> tuple[Path, Path]:
    """``a`` from a handshake; ``b`` mid-connection and 100 s *earlier* (its time must
    not be held back by ``a``'s)."""
    a = write_capture(tmp_path / "a.pcap", 1_700_000_100.0, [11, 12, 13], handshake=True)
    b = write_capture(tmp_path / "b.pcap", 1_700_000_000.0, [21, 22, 23], handshake=False)
    return a, b


class Records:
    def __init__(self) -> None:
        self.records: list[Any] = []

    def on_record(self, record: Any) -> None:
        self.records.append(record)


def test_two_captures_with_one_5_tuple_pair_each_with_its_own(
    captures: tuple[Path, Path],
) -> None:
    """Through ``run_sources``: the streams differ, and each answer names the value its
    own input carries (a shared stream id paired a's requests with b's answers)."""
    out = Records()
    hub = Hub(Pipeline(), [out])
    sources = [CaptureFileSource(path) for path in captures]
    for source in sources:
        source.open(hub)
    run_sources(hub, sources)
    hub.close()
    answers = [r for r in out.records if r.frame is not None and r.request is not None]
    assert [(r.stream.id, r.frame.pdu.values) for r in answers] == [
        (0, (11,)),
        (0, (12,)),
        (0, (13,)),
        (1, (21,)),
        (1, (22,)),
        (1, (23,)),
    ]
    assert all(r.latency == pytest.approx(0.002, abs=1e-5) for r in answers)
    timeouts = [r for r in out.records if r.event is not None and r.event.kind is EventKind.TIMEOUT]
    # each input's lone request times out at its own end, not at the other's
    assert [(r.stream.id, round(r.ts, 3)) for r in timeouts] == [
        (0, 1_700_000_100.346),
        (1, 1_700_000_000.346),
    ]


def _shift_text(text: str, records: int) -> str:
    """``text`` of a later input as one run numbers it: record numbers moved on."""
    return re.sub(r"record #(\d+)", lambda m: f"record #{int(m[1]) + records}", text)


def _shift(obj: dict[str, Any], records: int, streams: int) -> dict[str, Any]:
    obj = dict(obj)
    for key in ("index", "request_index", "line"):  # a monitor message's line: its index
        if isinstance(obj.get(key), int):
            obj[key] += records
    if isinstance(obj.get("stream"), int):
        obj["stream"] += streams
    for key in ("message", "line"):
        if isinstance(obj.get(key), str):
            obj[key] = _shift_text(obj[key], records)
    if isinstance(obj.get("notes"), list):
        obj["notes"] = [_shift_text(note, records) for note in obj["notes"]]
    if isinstance(obj.get("info"), dict) and isinstance(obj["info"].get("request_index"), int):
        obj["info"] = {**obj["info"], "request_index": obj["info"]["request_index"] + records}
    if isinstance(obj.get("name"), str):
        obj["name"] = re.sub(r"^#(\d+)", lambda m: f"#{int(m[1]) + streams}", obj["name"])
    obj.pop("file", None)  # the run's source: both inputs' names
    return obj


def test_read_of_two_captures_equals_reading_them_one_by_one(
    captures: tuple[Path, Path],
) -> None:
    a, b = captures
    text_a, text_b, text_ab = mbmon("read", a), mbmon("read", b), mbmon("read", a, b)
    assert text_ab.returncode == 0, text_ab.stderr
    records_a = len(mbmon("read", a, "--json").stdout.splitlines())
    assert text_ab.stdout == text_a.stdout + _shift_text(text_b.stdout, records_a)
    assert "record #16" in text_ab.stdout  # b's lone request, numbered after a's 10
    json_a, json_b = (mbmon("read", p, "--json").stdout.splitlines() for p in (a, b))
    json_ab = mbmon("read", a, b, "--json").stdout.splitlines()
    expected = [json.loads(line) for line in json_a]
    expected += [_shift(json.loads(line), records_a, 1) for line in json_b]
    assert [json.loads(line) for line in json_ab] == expected
    assert "2 unanswered" in text_ab.stderr and "on 2 streams" in text_ab.stderr


def _mcap_messages(path: Path) -> list[tuple[str, dict[str, Any]]]:
    from mcap.reader import make_reader

    from mbmon.io.mcap.proto import decode_payload  # log format 3: protobuf topics too

    with open(path, "rb") as f:
        messages = [
            (
                channel.topic,
                decode_payload(
                    schema.name if schema else "", channel.message_encoding, message.data
                ),
            )
            for schema, channel, message in make_reader(f).iter_messages(log_time_order=False)
        ]
    # the run's closing figures (one per log) are the run's, not an input's
    return [(topic, m) for topic, m in messages if m.get("event") != "stats"]


def test_an_mcap_log_of_two_captures_holds_each_as_alone(
    captures: tuple[Path, Path], tmp_path: Path
) -> None:
    a, b = captures
    for name, inputs in (("a", [a]), ("b", [b]), ("ab", [a, b])):
        done = mbmon("read", *inputs, "-q", "-w", tmp_path / f"{name}.mcap")
        assert done.returncode == 0, done.stderr
    log_a, log_b, log_ab = (_mcap_messages(tmp_path / f"{n}.mcap") for n in ("a", "b", "ab"))
    records_a = 1 + max(m["index"] for _t, m in log_a if isinstance(m.get("index"), int))
    expected = [(t, _shift(m, 0, 0)) for t, m in log_a]
    expected += [(t, _shift(m, records_a, 1)) for t, m in log_b]
    assert [(t, _shift(m, 0, 0)) for t, m in log_ab] == expected


def test_two_logs_replayed_in_one_run_keep_their_streams_apart(
    captures: tuple[Path, Path], tmp_path: Path
) -> None:
    """Recorded stream ids (both logs have stream 0) become the run's: the first log
    keeps its own, the second gets new ones; records equal each log decoded alone."""
    logs = []
    for path in captures:
        log = tmp_path / f"{path.stem}.mcap"
        assert mbmon("read", path, "-q", "-w", log).returncode == 0
        logs.append(log)

    def text_of(*paths: Path) -> str:
        out = io.StringIO()
        hub = Hub(Pipeline(), [ConsoleListener(out, View())])
        sources = [McapLogSource(path) for path in paths]
        for source in sources:
            source.open(hub)
        run_sources(hub, sources)
        hub.close()
        return out.getvalue()

    alone_a, alone_b, both = text_of(logs[0]), text_of(logs[1]), text_of(*logs)
    records_a = len(alone_a.splitlines())
    assert both == alone_a + _shift_text(alone_b, records_a)
    assert "= 21" in both and "= 11" in both


def test_a_recorded_answers_on_names_the_mapped_stream() -> None:
    """A proxy's ``connect`` names the stream its answers come on (``answers_on``): when
    the recorded ids are mapped, the name follows."""
    hub = Hub()
    hub.new_stream_id()  # another source holds 0
    recorded = hub.recorded_streams()
    client = Stream(0, Transport.TCP, "c", "s")
    connect = Event(0.0, client, EventKind.CONNECT, {"answers_on": 1, "note": "proxy"})
    mapped = recorded.item(connect)
    assert mapped.stream is not None
    assert (mapped.stream.id, mapped.info["answers_on"]) == (1, 2)
    chunk = recorded.item(Chunk(0.0, Stream(1, Transport.TCP, "c", "p"), Direction.S2C, b""))
    assert chunk.stream.id == 2
    # a source's ids never taken by another are kept
    assert Hub().recorded_streams().item(connect) is connect


def test_a_bad_input_among_several_stops_read_before_any_output(
    captures: tuple[Path, Path], tmp_path: Path
) -> None:
    """Every input is opened before any output: a missing, foreign or MCAP file among
    several is one line, exit status 1, nothing printed and no log written."""
    a, _b = captures
    notes = tmp_path / "notes.txt"
    notes.write_text("not a capture\n")
    log = tmp_path / "x.mcap"
    assert mbmon("read", a, "-q", "-w", log).returncode == 0
    mcap_input = log.rename(tmp_path / "earlier.mcap")
    for bad, words in (
        (tmp_path / "missing.pcap", "no such file"),
        (notes, "notes.txt"),
        (mcap_input, "is an MCAP log, not a capture: try 'mbmon replay"),
    ):
        done = mbmon("read", a, bad, "-w", log)
        assert done.returncode == 1, done.stderr
        assert words in done.stderr and "Traceback" not in done.stderr
        assert done.stdout == "" and not log.exists()
    twice = mbmon("read", "-", "-")
    assert twice.returncode == 2 and "stdin (-) can be read once" in twice.stderr
    debug = mbmon("read", a, a, "--debug-core", "-q")  # the core decides on them all
    assert "core: " in debug.stderr and "several inputs" not in debug.stderr


def test_two_logs_redecoded_through_log_sources_keep_their_streams_apart(
    captures: tuple[Path, Path], tmp_path: Path
) -> None:
    """``replay --redecode``'s source (io/logsource.LogSource, raw items) opened on a hub
    maps its recorded ids as McapLogSource does: two logs of one run stay apart."""
    from mbmon.io.logsource import LogSource
    from mbmon.io.mcap.reader import McapLog
    from mbmon.timefmt import TimeFormat

    logs = []
    for path in captures:
        log = tmp_path / f"{path.stem}.mcap"
        assert mbmon("read", path, "-q", "-w", log).returncode == 0
        logs.append(McapLog(log))
    try:
        out = Records()
        hub = Hub(Pipeline(), [out])
        sources = [LogSource(log, TimeFormat(), raw=True) for log in logs]
        for source in sources:
            source.open(hub)
        run_sources(hub, sources)
        hub.close()
    finally:
        for log in logs:
            log.close()
    answers = [r for r in out.records if r.frame is not None and r.request is not None]
    assert [(r.stream.id, r.frame.pdu.values[0]) for r in answers] == [
        (0, 11),
        (0, 12),
        (0, 13),
        (1, 21),
        (1, 22),
        (1, 23),
    ]


@settings(max_examples=200, deadline=None)
@given(
    st.lists(
        st.one_of(st.none(), st.integers(min_value=-1, max_value=12)),
        max_size=40,
    )
)
def test_the_allocator_never_gives_one_id_twice(asks: list[int | None]) -> None:
    """Any mix of new ids and claimed ones (None: ``new()``): all different, a claimed
    id kept when free, and never negative."""
    ids = StreamIds()
    given_out: list[int] = []
    for ask in asks:
        sid = ids.new() if ask is None else ids.claim(ask)
        if ask is not None and ask >= 0 and ask not in given_out:
            assert sid == ask
        given_out.append(sid)
    assert len(set(given_out)) == len(given_out)
    assert all(sid >= 0 for sid in given_out)
