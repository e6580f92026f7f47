"""How `mbmon read` hands lines to stdout (the console listener): blocks, live input,
UTF-8 written as bytes, any other encoding as text — always the same lines."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

from mbmon.format import View, json_line, record_line, record_to_json
from mbmon.model import Record
from mbmon.pipeline import Pipeline
from mbmon.sinks.console import BLOCK, ConsoleListener
from mbmon.sources.pcapfile import read_capture

REPO = Path(__file__).resolve().parents[1]
CAPTURE = REPO / "captures" / "hrss_ptp.pcap"


def _records() -> list[Record]:
    return list(Pipeline().run(read_capture(CAPTURE)))


def _emit(
    batches: Iterator[list[Record]],
    out: io.TextIOWrapper,
    as_json: bool,
    view: View,
    live: bool = False,
) -> None:
    """Each batch to the console listener as the hub hands it over, then close."""
    console = ConsoleListener(out, view, as_json=as_json, live=live)
    for batch in batches:
        console.on_records(batch)
    console.close()


def _stdout() -> tuple[io.TextIOWrapper, io.BytesIO]:
    """A text stream over a buffered binary one, like sys.stdout; and the bytes out."""
    raw = io.BytesIO()
    return io.TextIOWrapper(io.BufferedWriter(raw), encoding="utf-8", newline="\n"), raw


def test_lines_in_blocks_are_every_line_in_order() -> None:
    records = _records()
    batches = [records] * (2 * BLOCK // len(records) + 1)  # several blocks
    view = View(robot="127.0.0.1:502")
    for as_json, line in ((True, lambda r: json_line(record_to_json(r, view))), (False, None)):
        out, raw = _stdout()
        _emit(iter(batches), out, as_json, view)
        expected = [line(r) if line else record_line(r, view) for b in batches for r in b]
        assert raw.getvalue().decode().split("\n") == [*expected, ""]


def test_live_batches_are_written_before_the_next_one_is_asked_for() -> None:
    records = _records()
    out, raw = _stdout()
    seen: list[bytes] = []

    def batches(live_output: io.BytesIO) -> Iterator[list[Record]]:
        for record in records[:3]:
            yield [record]
            seen.append(live_output.getvalue())

    _emit(batches(raw), out, True, View(), live=True)
    assert [s.count(b"\n") for s in seen] == [1, 2, 3]
    out, raw = _stdout()
    seen.clear()
    _emit(batches(raw), out, True, View(), live=False)
    assert seen == [b"", b"", b""]  # a file: lines wait for a full block
    assert raw.getvalue().count(b"\n") == 3


def test_ctrl_c_during_a_write_leaves_no_empty_or_repeated_line() -> None:
    """A KeyboardInterrupt between any two steps of a write (Ctrl-C lands where it
    lands; here: just after the last line's terminator was added for the join):
    no empty line comes out (it breaks every JSON-lines reader), and no line twice."""
    records = _records()[:3]

    class InterruptedOnce(list):  # the waiting lines, as the listener keeps them
        interrupted = False

        def append(self, item: object) -> None:
            super().append(item)
            if not self.interrupted:
                self.interrupted = True
                raise KeyboardInterrupt

    out = io.StringIO()
    console = ConsoleListener(out, View(), live=True)
    console._lines = InterruptedOnce()
    try:
        console.on_records(records[:2])
    except KeyboardInterrupt:
        pass
    console.on_records(records[2:])
    console.close()
    lines = out.getvalue().split("\n")
    assert "" not in lines[:-1], lines
    assert len(set(lines)) == len(lines)
    assert lines[-2:] == [record_line(records[2], View()), ""]


def test_json_is_the_same_text_in_any_stdout_encoding() -> None:
    """UTF-8 stdout gets bytes made in UTF-8; another encoding gets the text."""

    def run(encoding: str) -> str:
        env = dict(os.environ, PYTHONIOENCODING=encoding)
        res = subprocess.run(
            [sys.executable, "-m", "mbmon", "read", str(CAPTURE), "--json"],
            capture_output=True,
            env=env,
            timeout=120,
            check=True,
        )
        return res.stdout.decode(encoding)

    utf8 = run("utf-8")
    assert "→" in utf8  # non-ASCII labels
    assert run("utf-16") == utf8
    view = View()
    assert utf8 == "".join(json_line(record_to_json(r, view)) + "\n" for r in _records())


def test_stdout_that_cannot_encode_the_text_gets_escapes_not_a_traceback() -> None:
    env = dict(os.environ, PYTHONIOENCODING="ascii")
    res = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", str(CAPTURE), "--json"],
        capture_output=True,
        env=env,
        timeout=120,
        check=True,
    )
    rows = [json.loads(line) for line in res.stdout.decode("ascii").splitlines()]
    assert "→" in rows[0]["line"]  # the JSON escape decodes to the real character
    assert b"Traceback" not in res.stderr
