"""The monitor's screen, headless (textual's Pilot) at 80x24, 120x30 and 200x60: panes,
lines seen whole, and every key the help lists, on the project's HRSS capture."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from monitor_records import hrss_items, records_of

from mbmon.format import View
from mbmon.model import RecordKind
from mbmon.monitor import MonitorFeed
from mbmon.monitor.app import MonitorApp
from mbmon.monitor.details import Details
from mbmon.monitor.widgets import HELP, HelpScreen, MonitorList

SIZES = [(80, 24), (120, 30), (200, 60)]


def _records() -> list[Any]:
    return records_of(hrss_items(), ["hrss"])


def _feed(records: list[Any]) -> MonitorFeed:
    feed = MonitorFeed(View(), title="mbmon test", profile=True)
    feed.on_records(records)
    return feed


def _drive(
    feed: MonitorFeed,
    size: tuple[int, int],
    script: Callable[[Any, MonitorApp], Awaitable[None]],
    **kwargs: Any,
) -> MonitorApp:
    app = MonitorApp(feed, **kwargs)

    async def main() -> None:
        async with app.run_test(size=size) as pilot:
            await pilot.pause()
            await script(pilot, app)

    asyncio.run(main())
    return app


def _list(app: MonitorApp) -> MonitorList:
    return app.query_one("#list", MonitorList)


async def _type(pilot: Any, text: str) -> None:
    for ch in text:
        await pilot.press({" ": "space", "-": "minus", ",": "comma"}.get(ch, ch))


@pytest.mark.parametrize("size", SIZES)
def test_panes_and_every_line_seen_whole(size: tuple[int, int]) -> None:
    records = _records()
    feed = _feed(records)
    seen: dict[str, Any] = {}

    async def script(pilot: Any, app: MonitorApp) -> None:
        await pilot.pause()  # the footer lays its keys out after the first refresh
        lst = _list(app)
        seen["rows"] = len(lst.rows)
        seen["list"] = lst.region.height > 2 and lst.display
        seen["details"] = app.query_one("#details").region.height > 2
        seen["side"] = app.query_one("#side").display
        seen["text"] = app.screen_text()
        # the longest line is wider than the list: → scrolls it, the details show it all
        widest = max(range(len(lst.rows)), key=lambda i: len(lst.rows[i].line))
        lst.select(widest, follow=False)
        await pilot.pause()
        line = lst.rows[widest].line
        seen["cut"] = len(line) + 2 > lst.size.width
        seen["whole"] = line in app.query_one("#details", Details).text()
        before = lst.x
        await pilot.press("right", "right")
        seen["sideways"] = lst.x > before
        await pilot.press("r")  # the robot panel and register image, at any size
        await pilot.pause()
        seen["side_r"] = app.query_one("#side").display
        seen["text_r"] = app.screen_text()

    _drive(feed, size, script)
    assert seen["rows"] == len(records)
    assert seen["list"] and seen["details"]
    text = seen["text"]
    assert "mbmon test" in text and "frames 56" in text  # the header
    assert "monitor: 61 lines" in text and "details" in text
    assert "space pause" in text  # the footer
    assert seen["cut"] and seen["whole"] and seen["sideways"]
    wide = size[0] >= 120
    assert seen["side"] is wide
    assert seen["side_r"] is not wide  # r toggles what the width chose
    side_text = text if wide else seen["text_r"]
    assert "A1    90.000" in side_text and "registers" in side_text


def test_pause_holds_the_view_while_counts_go_on() -> None:
    records = _records()
    feed = _feed(records[:20])
    seen: dict[str, Any] = {}

    async def script(pilot: Any, app: MonitorApp) -> None:
        await pilot.press("space")
        feed.on_records(records[20:])
        await pilot.pause(0.3)
        seen["paused_rows"] = len(_list(app).rows)
        seen["paused_header"] = app.screen_text().split("╭", 1)[0]
        await pilot.press("space")
        await pilot.pause(0.3)
        seen["rows"] = len(_list(app).rows)

    _drive(feed, (120, 30), script)
    assert seen["paused_rows"] == 20
    assert "PAUSED +41 new" in seen["paused_header"]
    assert "frames 56" in seen["paused_header"]  # counts went on
    assert seen["rows"] == len(records)


def test_search_next_previous_and_filter() -> None:
    records = _records()
    feed = _feed(records)
    seen: dict[str, Any] = {}

    async def script(pilot: Any, app: MonitorApp) -> None:
        lst = _list(app)
        await pilot.press("home", "slash")
        await _type(pilot, "write single")
        await pilot.press("enter")
        await pilot.pause()
        seen["first"] = lst.cursor
        await pilot.press("n")
        seen["next"] = lst.cursor
        await pilot.press("N")
        seen["back"] = lst.cursor
        await pilot.press("f")
        await _type(pilot, "--fc 16")
        await pilot.press("enter")
        await pilot.pause()
        seen["filtered"] = [e.record for e in lst.rows]
        seen["title"] = app.screen_text()
        await pilot.press("f", "ctrl+u")
        await _type(pilot, "--fc x")
        await pilot.press("enter")
        await pilot.pause()
        seen["kept"] = len(lst.rows)
        await pilot.press("f", "ctrl+u", "enter")
        await pilot.pause()
        seen["all"] = len(lst.rows)

    _drive(feed, (200, 60), script)
    lines = [e.line for e in feed.snapshot().entries]
    matches = [i for i, line in enumerate(lines) if "write single" in line.lower()]
    assert seen["first"] == matches[0] and seen["next"] == matches[1]
    assert seen["back"] == matches[0]
    fc16 = [r for r in records if r.frame is not None and r.frame.pdu.fc == 16]
    assert seen["filtered"] == fc16
    assert f"{len(fc16)} lines of {len(records)} (filter: --fc 16)" in seen["title"]
    assert seen["kept"] == len(fc16)  # a bad filter changes nothing
    assert seen["all"] == len(records)


def test_marks_jump_and_write_the_marked_range(tmp_path: Path) -> None:
    from mbmon.monitor import save_entries
    from mbmon.sinks.base import SinkContext

    records = _records()
    feed = _feed(records)
    ctx = SinkContext(view=View())
    out = tmp_path / "marked.jsonl"
    seen: dict[str, Any] = {}

    async def script(pilot: Any, app: MonitorApp) -> None:
        lst = _list(app)
        await pilot.press("home", "down", "down", "m")
        await pilot.press(*["down"] * 5, "m", "end")
        await pilot.press("apostrophe")
        seen["jump1"] = lst.cursor
        await pilot.press("apostrophe")
        seen["jump2"] = lst.cursor
        await pilot.press("w")
        await _type(pilot, str(out))
        await pilot.press("enter")
        await pilot.pause()

    _drive(feed, (120, 30), script,
           save=lambda path, entries: save_entries(path, entries, feed, ctx))  # fmt: skip
    assert (seen["jump1"], seen["jump2"]) == (2, 7)
    written = [json.loads(line) for line in out.read_text().splitlines()]
    assert [o["index"] for o in written] == [r.index for r in records[2:8]]


def test_write_mcap_with_raw_bytes(tmp_path: Path) -> None:
    """w to .mcap: the kept records and their raw chunks, read back by mbmon's reader."""
    from mbmon.commands.common import make_annotator
    from mbmon.hub import Hub
    from mbmon.io.mcap.reader import McapLog
    from mbmon.io.replay import logged_records, raw_items
    from mbmon.monitor import save_entries
    from mbmon.pipeline import Pipeline
    from mbmon.sinks.base import SinkContext

    annotator = make_annotator(["hrss"])
    feed = MonitorFeed(View(), annotator=annotator)
    hub = Hub(Pipeline(annotator), [feed])
    hub.run_items(hrss_items())
    entries = feed.snapshot().entries
    out = tmp_path / "kept.mcap"
    said = save_entries(str(out), entries, feed, SinkContext(view=View(), profile_specs=["hrss"]))
    assert said == f"wrote {len(entries)} lines to {out}"
    with McapLog(out) as log:
        assert [r.text for r in logged_records(log)] == [e.line for e in entries]
        assert sum(1 for _ in raw_items(log)) > 0


def test_snapshot_diff_shows_the_changed_register() -> None:
    records = _records()
    # R200 = 1 (06 00 C8 00 01) is written after the snapshot
    at = next(i for i, r in enumerate(records) if r.kind is RecordKind.REQUEST
              and r.frame.pdu.raw == bytes.fromhex("0600C80001"))  # fmt: skip
    feed = _feed(records[:at])
    seen: dict[str, Any] = {}

    async def script(pilot: Any, app: MonitorApp) -> None:
        await pilot.press("d")  # no snapshot yet: says so, shows nothing new
        await pilot.press("s")
        feed.on_records(records[at : at + 3])  # the write, its command step, its answer
        await pilot.pause(0.3)
        await pilot.press("d")
        await pilot.pause()
        seen["text"] = app.screen_text()

    _drive(feed, (120, 30), script)
    text = seen["text"]
    assert "registers: changed since snapshot" in text
    assert "changed since the snapshot: 1" in text
    assert "R200 0 → 1" in text


def test_help_and_quit() -> None:
    feed = _feed(_records())
    seen: dict[str, Any] = {}

    async def script(pilot: Any, app: MonitorApp) -> None:
        await pilot.press("question_mark")
        await pilot.pause()
        seen["help"] = isinstance(app.screen, HelpScreen)
        seen["text"] = app.screen_text()
        await pilot.press("escape")
        seen["back"] = not isinstance(app.screen, HelpScreen)
        await pilot.press("q")
        await pilot.pause()

    app = _drive(feed, (120, 40), script)
    assert seen["help"] and seen["back"]
    for key in ("space", "/", "n  N", "f", "s", "d", "m", "'", "w", "q  ctrl+c"):
        assert f"  {key} " in HELP and key in seen["text"]
    assert app.return_code == 0 and app._exit


def test_untrusted_bytes_never_become_markup() -> None:
    from mbmon.model import Event, EventKind

    feed = MonitorFeed(View())
    from mbmon.pipeline import Pipeline

    pipeline = Pipeline()
    evil = "[bold red]x[/] [link=http://e]y[/link]"
    feed.on_records(pipeline.feed(Event(1.0, None, EventKind.NOTICE, {"message": evil})))
    seen: dict[str, str] = {}

    async def script(pilot: Any, app: MonitorApp) -> None:
        seen["text"] = app.screen_text()

    _drive(feed, (200, 30), script)
    assert evil in seen["text"]
