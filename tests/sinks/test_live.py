"""The rich live monitor renders what the records say (a recording rich Console).

Records are real: the HRSS capture shipped in captures/ through the HRSS profile
(the ``hrss_stream`` fixture), and the byte session of sink_records.
"""

from __future__ import annotations

import io

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
