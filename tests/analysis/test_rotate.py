"""Rotating -w files (mbmon.analysis.rotate): every format, each file finished and valid on
its own, named with its start time, the oldest removed beyond --keep, and nothing lost or
doubled at a rotation (the counts across the files equal one file's)."""

from __future__ import annotations

import calendar
import csv
import json
import re
import time
from pathlib import Path

import pytest
from mbmon_cli import mbmon

from mbmon.analysis.rotate import RotatingSink, parse_rotate, rotated_name
from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.sinks.base import SinkContext

REPO = Path(__file__).resolve().parents[2]
START = calendar.timegm((2026, 11, 26, 10, 20, 0)) + 0.5  # 10:20:00.5 UTC
NAME = re.compile(r"^cell_(\d{5})_(\d{8}T\d{6}Z)\.(\w+)$")


def polling(path: Path, *, hours: float = 3.0, period: float = 10.0) -> int:
    """A client polling R0..R1 every ``period`` s for ``hours`` (a new connection each
    hour, so connect and disconnect events fall on both sides of boundaries); returns
    the number of transactions."""
    n = 0
    with PcapWriter(path) as out:
        t = START
        end = START + hours * 3600
        conn = 0
        while t < end:
            conv = TcpConversation(f"10.0.0.9:{40000 + conn}", "10.0.0.1:502")
            for frame in conv.open():
                out.write(t, frame)
            hour_end = min(end, t + 3600 - 1)
            while t < hour_end:
                n += 1
                t += period
                out.write(
                    t, conv.send(True, encode_adu(n & 0xFFFF, 1, bytes.fromhex("0300000002")))
                )
                out.write(
                    t + 0.004,
                    conv.send(False, encode_adu(n & 0xFFFF, 1, bytes.fromhex("030400010002"))),
                )
            for frame in conv.close():
                out.write(t + 0.01, frame)
            t += 1
            conn += 1
    return n


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    path = tmp_path_factory.mktemp("rot") / "cell.pcap"
    return path, polling(path)


def ring(directory: Path, suffix: str) -> list[Path]:
    return sorted(p for p in directory.iterdir() if NAME.match(p.name) and p.suffix == suffix)


def mcap_counts(path: Path) -> dict[str, int]:
    from mcap.reader import make_reader

    counts: dict[str, int] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None, f"{path.name} was not finished"
        for _schema, channel, _message in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def frames_of(path: Path) -> list[str]:
    """The frames ``mbmon read`` finds in a pcap (a check that it is a valid capture)."""
    run = mbmon("read", str(path), "--json", "--no-detect")
    assert run.returncode == 0, run.stderr
    return [
        json.loads(line)["pdu"] for line in run.stdout.splitlines() if '"kind":"event"' not in line
    ]


def counted(path: Path) -> object:
    """What one file holds, in a form whose sum over files is comparable."""
    suffix = path.suffix
    if suffix == ".mcap":
        return mcap_counts(path)
    if suffix == ".csv":
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
        assert rows[0][0] and all(len(r) == len(rows[0]) for r in rows)  # a header, whole rows
        return len(rows) - 1
    if suffix == ".pcap":
        return len(frames_of(path))
    text = path.read_text("utf-8")
    assert text.endswith("\n")  # no half line
    if suffix == ".jsonl":
        for line in text.splitlines():
            json.loads(line)
    return len(text.splitlines())


def add(total: object, part: object) -> object:
    if isinstance(part, dict):
        assert isinstance(total, dict)
        for key, value in part.items():
            total[key] = total.get(key, 0) + value
        return total
    assert isinstance(total, int) and isinstance(part, int)
    return total + part


@pytest.mark.parametrize("suffix", [".mcap", ".jsonl", ".csv", ".txt", ".pcap"])
def test_hourly_files_hold_what_one_file_holds(
    suffix: str, capture: tuple[Path, int], tmp_path: Path
) -> None:
    cap, transactions = capture
    single = tmp_path / f"single{suffix}"
    run = mbmon("read", str(cap), "-q", "-w", str(single))
    assert run.returncode == 0, run.stderr
    rotated = tmp_path / "r"
    rotated.mkdir()
    run = mbmon("read", str(cap), "-q", "-w", str(rotated / f"cell{suffix}"), "--rotate", "1h")
    assert run.returncode == 0, run.stderr
    files = ring(rotated, suffix)
    # 10:20 .. 13:20 UTC: four hours touched, four files, named in order with their start
    assert [NAME.match(p.name).group(1) for p in files] == ["00001", "00002", "00003", "00004"]
    stamps = [NAME.match(p.name).group(2) for p in files]
    assert stamps[0] == "20261126T102000Z"
    # the later files begin with the first item of their hour (polls drift by seconds)
    assert [stamp[:11] for stamp in stamps[1:]] == ["20261126T11", "20261126T12", "20261126T13"]
    assert all(stamp[11:13] == "00" for stamp in stamps[1:])
    assert not (rotated / f"cell{suffix}").exists()
    total: object = {} if suffix == ".mcap" else 0
    for path in files:
        total = add(total, counted(path))
    assert total == counted(single)
    if suffix == ".mcap":
        assert total["/modbus/frames"] == 2 * transactions  # type: ignore[index]
    if suffix == ".pcap":
        assert total == 2 * transactions


def test_each_file_starts_at_its_boundary(capture: tuple[Path, int], tmp_path: Path) -> None:
    """The JSON lines of each hourly file lie in that hour (the file's name says which)."""
    cap, _ = capture
    run = mbmon("read", str(cap), "-q", "-w", str(tmp_path / "cell.jsonl"), "--rotate", "1h")
    assert run.returncode == 0, run.stderr
    for path in ring(tmp_path, ".jsonl"):
        times = [json.loads(line)["time"] for line in path.read_text().splitlines()]
        stamp = NAME.match(path.name).group(2)
        start = calendar.timegm(time.strptime(stamp, "%Y%m%dT%H%M%SZ"))
        assert int(min(times)) == start or (start % 3600 == 0 and min(times) >= start)
        assert max(times) < (start // 3600 + 1) * 3600


def test_keep_removes_the_oldest(capture: tuple[Path, int], tmp_path: Path) -> None:
    cap, _ = capture
    run = mbmon(
        "read", str(cap), "-q", "-w", str(tmp_path / "cell.mcap"), "--rotate", "1h", "--keep", "2"
    )
    assert run.returncode == 0, run.stderr
    files = ring(tmp_path, ".mcap")
    assert [NAME.match(p.name).group(1) for p in files] == ["00003", "00004"]
    for path in files:
        mcap_counts(path)  # finished


def test_size_rotation(capture: tuple[Path, int], tmp_path: Path) -> None:
    cap, _ = capture
    run = mbmon("read", str(cap), "-q", "-w", str(tmp_path / "cell.jsonl"), "--rotate", "200kB")
    assert run.returncode == 0, run.stderr
    files = ring(tmp_path, ".jsonl")
    assert len(files) >= 3
    lines = 0
    for path in files:
        size = path.stat().st_size
        # a file is looked at every 256 records (or on a tick): it may exceed a little
        assert size < 200_000 + 256 * 1000, (path.name, size)
        lines += counted(path)  # type: ignore[operator]
    single = tmp_path / "one.jsonl"
    assert mbmon("read", str(cap), "-q", "-w", str(single)).returncode == 0
    assert lines == counted(single)


def test_both_a_period_and_a_size(capture: tuple[Path, int], tmp_path: Path) -> None:
    cap, _ = capture
    run = mbmon(
        "read",
        str(cap),
        "-q",
        "-w",
        str(tmp_path / "cell.txt"),
        "--rotate",
        "1h",
        "--rotate",
        "50kB",
    )
    assert run.returncode == 0, run.stderr
    assert len(ring(tmp_path, ".txt")) > 4


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--keep", "3"], "--keep needs --rotate"),
        (["--rotate", "soon"], "neither a duration"),
        (["--rotate", "5"], "give a unit"),
        (["--rotate", "1h", "--rotate", "2h"], "one duration at most"),
    ],
)
def test_bad_rotation_is_a_usage_error(args: list[str], message: str, tmp_path: Path) -> None:
    cap = tmp_path / "x.pcap"
    polling(cap, hours=0.01)
    run = mbmon("read", str(cap), "-q", "-w", str(tmp_path / "x.jsonl"), *args)
    assert run.returncode == 2 and message in run.stderr, run.stderr
    assert not list(tmp_path.glob("x*.jsonl"))
    assert mbmon("read", str(cap), "-q", "--rotate", "1h").returncode == 2  # no -w


def test_durations() -> None:
    from mbmon.timefmt import TimeParseError, parse_duration

    assert [parse_duration(t) for t in ("30s", "250ms", "1m30s", "1h", "7d", "2")] == [
        30.0, 0.25, 90.0, 3600.0, 604800.0, 2.0,
    ]  # fmt: skip
    for bad in ("", "soon", "0s", "1y"):
        with pytest.raises(TimeParseError):
            parse_duration(bad)


def test_names_and_values() -> None:
    assert parse_rotate(["1h"]) == (3600.0, None)
    assert parse_rotate(["100MB", "30min"]) == (1800.0, 100_000_000)
    assert parse_rotate(["1GiB"]) == (None, 1 << 30)
    assert rotated_name(Path("/d/cell.mcap"), 7, START).name == "cell_00007_20261126T102000Z.mcap"


def test_the_hub_calls_only_the_hooks_the_format_has(tmp_path: Path) -> None:
    """A rotating pcap has on_chunk/on_event and no record hook; a rotating jsonl the
    other way round (the hub looks hooks up once, by name)."""
    pcap = RotatingSink(tmp_path / "a.pcap", SinkContext(), every=3600)
    jsonl = RotatingSink(tmp_path / "a.jsonl", SinkContext(), every=3600)
    assert callable(getattr(pcap, "on_chunk", None)) and getattr(pcap, "on_record", None) is None
    assert callable(getattr(jsonl, "on_record", None)) and getattr(jsonl, "on_chunk", None) is None
    pcap.close()
    jsonl.close()
    assert list(tmp_path.iterdir()) == []  # nothing came: no empty file


def test_a_file_whose_period_ended_is_finished_on_the_next_tick(tmp_path: Path) -> None:
    """Live: the line goes quiet after a few polls; a tick past the hour finishes the
    file (an MCAP with its summary) without waiting for the next item, and no empty
    file is begun."""
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline
    from mbmon.sources.pcapfile import read_capture

    cap = tmp_path / "short.pcap"
    polling(cap, hours=0.01)  # 10:20:00.5 .. about 10:20:36
    sink = RotatingSink(tmp_path / "cell.mcap", SinkContext(), every=3600)
    hub = Hub(Pipeline())
    hub.add_listener(sink)
    for item in read_capture(cap):
        hub.feed(item)
    hub.tick(START + 600)  # within the hour: the file stays open
    assert sink.files and mcap_counts_or_none(sink.files[0]) is None
    hub.tick(START + 2400)  # 11:00:00.5: the hour is over
    counts = mcap_counts(sink.files[0])
    assert counts["/modbus/frames"] > 0
    hub.close()
    assert len(sink.files) == 1 and len(list(tmp_path.glob("cell_*"))) == 1


def mcap_counts_or_none(path: Path) -> dict[str, int] | None:
    """The counts of a finished MCAP, None while it is still being written."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except Exception:
            return None
    return None if summary is None else mcap_counts(path)
