"""MonitorFeed, the monitor's hub listener: the lines read prints, counts, the register
image, the paired answers, the HRSS panel's written registers; on real captures."""

from __future__ import annotations

from monitor_records import hrss_items, records_of

from mbmon.format import View, record_line
from mbmon.hub import Hub
from mbmon.model import Chunk, RecordKind
from mbmon.monitor.feed import MonitorFeed, RegisterImage
from mbmon.semantics.hrss.render import parameter_rows


def _fed(profiles: list[str], keep: int = 10_000, cut: bytes | None = None) -> MonitorFeed:
    """The HRSS capture through a hub with the feed (up to the chunk holding ``cut``)."""
    from mbmon.commands.common import make_annotator
    from mbmon.pipeline import Pipeline

    items = hrss_items()
    if cut is not None:
        at = next(i for i, x in enumerate(items) if isinstance(x, Chunk) and cut in x.data)
        items = items[: at + 1]
    annotator = make_annotator(profiles)
    feed = MonitorFeed(View(), annotator=annotator, keep=keep, profile=bool(profiles))
    hub = Hub(Pipeline(annotator), [feed])
    for item in items:
        hub.feed(item)
    if cut is None:
        hub.finish()
    hub.tick(hub.now + 1)
    return feed


def test_lines_are_the_lines_read_prints_and_counts_add_up() -> None:
    feed = _fed(["hrss"])
    records = records_of(hrss_items(), ["hrss"])
    snap = feed.snapshot()
    assert [e.line for e in snap.entries] == [record_line(r, View()) for r in records]
    kinds = [r.kind for r in records]
    assert snap.counts["requests"] == kinds.count(RecordKind.REQUEST)
    assert snap.counts["responses"] == kinds.count(RecordKind.RESPONSE)
    assert snap.counts["exceptions"] == kinds.count(RecordKind.EXCEPTION)
    assert snap.counts["frames"] == sum(r.frame is not None for r in records)
    assert snap.ended is False
    feed.end()
    assert feed.snapshot().ended


def test_keeps_the_last_n_and_their_answers() -> None:
    feed = _fed([], keep=10)
    snap = feed.snapshot()
    assert len(snap.entries) == 10 and snap.total > 10
    assert [e.seq for e in snap.entries] == list(range(snap.total - 10, snap.total))
    kept = {e.record.index for e in snap.entries}
    # every answer kept is found from its request; none of a request no longer kept
    for request_index, answer in snap.answers.items():
        assert answer.record.request_index == request_index
        assert answer.record.index in kept
    requests = [e for e in snap.entries if e.record.kind is RecordKind.REQUEST]
    answered = [e for e in requests if e.record.index in snap.answers]
    assert answered, "the kept requests' answers are paired"


def test_register_image_from_reads_and_answered_writes() -> None:
    records = records_of(hrss_items(), [])
    image = RegisterImage()
    for r in records:
        image.take(r)
    values = image.values()
    server = next(r.frame.stream.server for r in records if r.frame is not None)
    # R100 written 90 (06 00 64 00 5A, answered), the command block R201.. written
    assert values[(server, 1, "holding_register", 100)] == 90
    writes = [r for r in records if r.kind is RecordKind.REQUEST and r.frame.pdu.fc == 0x10
              and r.frame.pdu.address == 201]  # fmt: skip
    block = writes[-1].frame.pdu.values
    for i, v in enumerate(block):
        assert values[(server, 1, "holding_register", 201 + i)] == v
    # coils read 0..7 (01 01 01: coil 0 on) and the discrete inputs read
    assert values[(server, 1, "coil", 0)] in (0, 1)
    assert any(k[2] == "discrete_input" for k in values)
    # R200 went 0 -> 1 -> 0: its cell changed after it was first seen
    cell = image.cells[(server, 1, "holding_register", 200)]
    assert cell.changed > cell.first


def test_robot_panel_rows_come_from_the_hrss_session() -> None:
    feed = _fed(["hrss"])
    snap = feed.snapshot()
    assert snap.state.get("a1") is not None and snap.command is not None
    rows = {regs: (name, value, ok) for regs, name, value, ok in snap.parameters}
    assert rows["R201"] == ("command", "PTP (0)", True)
    assert rows["R203..R204"] == ("A1", "90 deg", True)
    assert rows["R200"] == ("execute", "Ready (0)", True)
    assert snap.panel_title == "command registers R200..R251 as written"


def test_a_write_not_answered_yet_is_marked() -> None:
    feed = _fed(["hrss"], cut=bytes.fromhex("1000C9001A34"))
    rows = {regs: (value, ok) for regs, _name, value, ok in feed.snapshot().parameters}
    assert rows["R201"] == ("PTP (0)", False)
    assert rows["R203..R204"] == ("90 deg", False)
    assert rows["R200"] == ("Ready (0)", True)


def test_parameter_rows_without_a_known_layout() -> None:
    assert parameter_rows({}) == []
    rows = parameter_rows({201: 999, 250: 7}, frozenset({250}))
    assert ("R201", "command", "command 999 (999)", True) in rows
    assert ("R250", "", "7", False) in rows


def test_figures_and_header_text() -> None:
    feed = MonitorFeed(View(), title="mbmon t")
    feed.set_figures({"kernel drops": 3, "open connections": 2})
    text = feed.header_text()
    assert text.startswith("mbmon t  0.0 frames/s  frames 0")
    assert "open connections 2" in text and "kernel drops 3" in text
    assert text.count("open connections") == 1


def test_the_default_keeps_ten_thousand_lines() -> None:
    from mbmon.monitor.feed import KEEP

    records = records_of(hrss_items(), [])
    feed = MonitorFeed(View())
    assert KEEP >= 10_000
    fed = 0
    while fed < KEEP + 2_000:
        feed.on_records(records)
        fed += len(records)
    snap = feed.snapshot()
    assert len(snap.entries) == KEEP and snap.total == fed
    assert snap.entries[-1].seq == fed - 1
