"""One sink contract: a sink registered once in ``SINKS`` serves ``read -w`` and ``export -o``.

The toy sink below is not part of mbmon: the test registers it for the suffix
``.toy`` and runs the real command line (in this process, so that the
registration holds) through ``read -w x.toy`` and ``export log.mcap -o y.toy``.
It knows nothing of logs: it has the listener hooks a sink has and takes its
text from :mod:`mbmon.format`, as a sink should; ``export`` hands it the
records a log stored, ``read`` the records it decodes, and the files agree.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import IO

import pytest

from mbmon.cli import main
from mbmon.format import record_line, record_to_json
from mbmon.model import Record
from mbmon.sinks.base import SINKS, SinkContext

CAPTURES = Path(__file__).resolve().parents[2] / "captures"


class ToySink:
    """One line per record: its index, kind, time and monitor line; one ``# closed``
    line at the end (so a file that was never closed shows it)."""

    def __init__(self, path: Path, ctx: SinkContext) -> None:
        self.view = ctx.view
        self._f: IO[str] = open(path, "w", encoding="utf-8")

    def on_record(self, record: Record) -> None:
        obj = record_to_json(record, self.view)
        self._f.write(
            f"{record.index} {record.kind.value} {obj['time']} {record_line(record, self.view)}\n"
        )

    def close(self) -> None:
        self._f.write("# closed\n")
        self._f.close()


@pytest.fixture
def toy(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(SINKS, ".toy", (__name__, "ToySink"))


def run(*argv: str | Path) -> int:
    return main([str(a) for a in argv])


@pytest.mark.parametrize("capture", ["hrss_ptp.pcap", "hrss_rtu.pcap", "sim_exceptions.pcap"])
def test_a_registered_sink_serves_read_and_export_alike(
    toy: None, tmp_path: Path, capture: str, capsys: pytest.CaptureFixture[str]
) -> None:
    source = CAPTURES / capture
    if not source.exists():
        pytest.skip(f"captures/{capture} absent")
    live, log, exported = tmp_path / "live.toy", tmp_path / "cell.mcap", tmp_path / "exported.toy"
    assert run("read", source, "-q", "-w", live, "-w", log) == 0
    assert run("export", log, "-o", exported) == 0
    lines = live.read_text(encoding="utf-8").splitlines()
    assert len(lines) > 5 and lines[-1] == "# closed"
    assert exported.read_text(encoding="utf-8") == live.read_text(encoding="utf-8")
    capsys.readouterr()


def test_export_filters_and_times_reach_the_registered_sink(
    toy: None, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--fc`` and ``-t`` of export shape what the sink gets, as for the built-in formats."""
    source = CAPTURES / "hrss_ptp.pcap"
    if not source.exists():
        pytest.skip("captures/hrss_ptp.pcap absent")
    log, toy_out, jsonl = tmp_path / "cell.mcap", tmp_path / "x.toy", tmp_path / "x.jsonl"
    assert run("read", source, "-q", "-w", log) == 0
    for out in (toy_out, jsonl):
        assert run("export", log, "-o", out, "--fc", "16", "-t", "r") == 0
    objs = [json.loads(line) for line in jsonl.read_text(encoding="utf-8").splitlines()]
    rows = toy_out.read_text(encoding="utf-8").splitlines()
    assert rows[-1] == "# closed" and len(rows) - 1 == len(objs) > 0
    for row, obj in zip(rows, objs, strict=False):
        index, kind, _time, line = row.split(" ", 3)
        assert (int(index), kind, line) == (obj["index"], obj["kind"], obj["line"])
        assert obj["fc"] == 16 and ":" not in line.split()[0]  # -t r: seconds from the start
    capsys.readouterr()
