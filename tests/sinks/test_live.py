"""The rich live monitor renders what the records say (a recording rich Console).

Records are real: the HRSS capture shipped in captures/ through the HRSS profile
(the ``hrss_stream`` fixture), and the byte session of sink_records.
"""

from __future__ import annotations

import io

import pytest
from rich.console import Console

from mbmon.format import View, record_line
from mbmon.hub import Hub
from mbmon.model import Direction as D
from mbmon.model import Frame, Kind, Pdu, Record, RecordKind, Stream, Transport
from mbmon.sinks.live import LiveMonitor


def _records(stream: list) -> list[Record]:
    return [item for item in stream if isinstance(item, Record)]


def _render(monitor: LiveMonitor, console: Console) -> str:
    console.print(monitor.render())
    return console.export_text()


def test_live_monitor_lines_header_and_state_panel(hrss_stream: list) -> None:
    records = _records(hrss_stream)
    console = Console(record=True, width=400, height=60, color_system=None)
    view = View()
    monitor = LiveMonitor(view, console, title="mbmon test", state_panel=True, start=False)
    for i in range(0, len(records), 7):  # batches, as the hub gives them
        monitor.on_records(records[i : i + 7])
    monitor.set_figure("kernel drops", 0)
    text = _render(monitor, console)

    frames = [r for r in records if r.frame is not None]
    exceptions = [r for r in records if r.kind is RecordKind.EXCEPTION]
    assert f"frames {len(frames)}" in text
    assert f"exceptions {len(exceptions)}" in text
    assert "kernel drops 0" in text
    # the newest lines, exactly as the console would print them, are on screen
    for record in records[-10:]:
        assert record_line(record, view) in text
    assert record_line(records[0], view) not in text  # scrolled away (200 kept, 60 rows)
    assert len(monitor.lines) == min(200, len(records))
    # the state panel: the last robot state and the last command with its outcome
    state: dict[str, float] = {}
    for record in records:
        if record.state:
            state.update(record.state)
    assert state, "the HRSS capture has robot state"
    assert f"A1 {state['a1']:9.3f}" in text
    assert (f"X {state['x']:9.3f}" if "x" in state else "X   —") in text
    assert f"speed {state['speed_pct']:.0f} %" in text
    commands = [r.command for r in records if r.command is not None]
    assert commands
    assert commands[-1].text in text and f"[{commands[-1].phase.value}" in text


def test_live_monitor_counts_and_rate_from_the_session(session_stream: list) -> None:
    records = _records(session_stream)
    console = Console(record=True, width=200, height=40, color_system=None)
    monitor = LiveMonitor(View(), console, start=False)
    monitor.on_tick(10.0)
    monitor.on_records(records)
    monitor.on_tick(11.0)
    frames = sum(1 for r in records if r.frame is not None)
    assert monitor.rate == frames
    text = _render(monitor, console)
    assert f"{float(frames):.1f} frames/s" in text
    assert "noise bytes" in text and "robot" not in text  # no state panel without state


def test_untrusted_bytes_never_become_markup() -> None:
    evil = Stream(0, Transport.TCP, "[bold red]10.0.0.1:1[/]", "[link=http://x]y[/link]:502")
    pdu = Pdu(bytes.fromhex("0300000001"), 3, Kind.REQUEST, address=0, count=1)
    frame = Frame(1.0, evil, D.C2S, 1, 7, pdu, b"", None)
    record = Record(0, 1.0, RecordKind.REQUEST, evil, frame=frame, notes=("[blink]note[/blink]",))
    console = Console(record=True, width=200, height=30, color_system=None)
    monitor = LiveMonitor(View(), console, start=False)
    monitor.on_records([record])
    text = _render(monitor, console)
    assert "[bold red]10.0.0.1:1[/]" in text
    assert "[blink]note[/blink]" in text
    assert "[link=http://x]y[/link]:502" in text


def test_live_screen_runs_as_a_hub_listener_without_taking_stdout(session_stream: list) -> None:
    screen = io.StringIO()
    console = Console(file=screen, force_terminal=True, width=120, height=30)
    monitor = LiveMonitor(View(), console, title="mbmon live")
    hub = Hub()
    hub.add_listener(monitor)
    items = [item for item in session_stream if not isinstance(item, Record)]
    hub.run_items(items)
    hub.tick(items[-1].ts + 1)
    hub.close()
    assert not hub.failures
    assert "mbmon live" in screen.getvalue() and "03 00 C8 00 02" in screen.getvalue()


# --------------------------------------------------------------------------- written parameters


def _hrss_run(cut: bytes | None = None) -> tuple[object, list[Record], list]:
    """The HRSS capture through a real pipeline with the HRSS profile, stopped just after
    the chunk that contains ``cut`` (when given): (annotator, records, items)."""
    from sink_records import REPO, run_pipeline

    from mbmon.cli import make_annotator
    from mbmon.model import Chunk
    from mbmon.sources.pcapfile import read_capture

    capture = REPO / "captures" / "hrss_ptp.pcap"
    if not capture.exists():
        pytest.skip("captures/hrss_ptp.pcap absent")
    items = list(read_capture(capture))
    if cut is not None:
        at = next(i for i, x in enumerate(items) if isinstance(x, Chunk) and cut in x.data)
        items = items[: at + 1]
    annotator = make_annotator(["hrss"])
    if cut is None:
        return annotator, _records(run_pipeline(items, annotator)), items
    from mbmon.pipeline import Pipeline

    pipeline = Pipeline(annotator)  # not finished: the last request stays unanswered
    records = [r for item in items for r in pipeline.feed(item)]
    return annotator, records, items


def _written_block(records: list[Record]) -> tuple[int, tuple[int, ...]]:
    """Address and values of the client's last Write Multiple Registers request at R201."""
    writes = [
        r.frame.pdu
        for r in records
        if r.kind is RecordKind.REQUEST and r.frame is not None and r.frame.pdu.fc == 0x10
        and r.frame.pdu.address == 201
    ]  # fmt: skip
    assert writes, "the capture writes a command block at R201"
    pdu = writes[-1]
    assert pdu.address is not None and pdu.values is not None
    return pdu.address, pdu.values


def test_state_panel_shows_the_written_parameter_registers_by_their_hrss_names() -> None:
    annotator, records, _ = _hrss_run()
    console = Console(record=True, width=200, height=60, color_system=None)
    monitor = LiveMonitor(View(), console, state_panel=True, start=False, annotator=annotator)
    monitor.on_records(records)
    text = _render(monitor, console)

    address, values = _written_block(records)
    word = {address + i: v for i, v in enumerate(values)}
    a1 = (word[203] | word[204] << 16) / 1000  # i32, low word first (manual Appendix II)
    assert "R201 command PTP (0)" in text  # R201 = 0: PTP (Table 16)
    assert word[202] == 0 and "R202 point_type Joint (0)" in text
    assert f"R203..R204 A1 {a1:g} deg" in text
    assert f"R215 speed {word[215]}%" in text and f"R216 acc {word[216]}%" in text
    assert f"R217 tool {word[217]}" in text and f"R218 base {word[218]}" in text
    # the command the monitor line shows is the one the registers hold
    assert f"Vel={word[215]}%" in text and f"TOOL[{word[217]}] BASE[{word[218]}]" in text
    # R200 was last written 0 (reset after the command): the image says so
    assert "R200 execute Ready (0)" in text
    assert " ?" not in text.split("command registers", 1)[1].split("monitor", 1)[0]


def test_a_write_not_answered_yet_is_marked() -> None:
    annotator, records, _ = _hrss_run(cut=bytes.fromhex("1000C9001A34"))
    last = [r for r in records if r.frame is not None][-1]
    assert last.kind is RecordKind.REQUEST and last.frame.pdu.address == 201  # not answered
    console = Console(record=True, width=200, height=60, color_system=None)
    monitor = LiveMonitor(View(), console, state_panel=True, start=False, annotator=annotator)
    monitor.on_records(records)
    text = _render(monitor, console)
    assert "R201 command PTP (0) ?" in text
    assert "R203..R204 A1 90 deg ?" in text
    assert "R200 execute Ready (0)" in text and "R200 execute Ready (0) ?" not in text


def test_no_parameter_panel_without_hrss_sessions(session_stream: list) -> None:
    from mbmon.sinks.live import parameter_rows

    console = Console(record=True, width=200, height=40, color_system=None)
    monitor = LiveMonitor(View(), console, state_panel=True, start=False, annotator=None)
    monitor.on_records(_records(session_stream))
    assert "command registers" not in _render(monitor, console)
    assert parameter_rows({}) == []
    # a register outside every layout keeps its raw word; an unknown command says so
    rows = parameter_rows({201: 999, 250: 7}, frozenset({250}))
    assert ("R201", "command", "command 999 (999)", True) in rows
    assert ("R250", "", "7", False) in rows
