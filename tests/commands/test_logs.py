"""End to end through the CLI (subprocesses): read -w LOG.mcap, replay, info, export, signals.

Round trip: ``read CAPTURE -w x.mcap`` then ``replay x.mcap --json`` prints what
``read CAPTURE --json`` printed, for every capture in ``captures/`` and
``../shared/captures/real/``. A recording killed with SIGKILL keeps every
record older than a second; SIGINT and SIGTERM leave finished, indexed files.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from format4 import MARKS
from long_capture import signal_while_logging, write_long_capture
from mcap.reader import make_reader

from mbmon.io.mcap.reader import McapLog

REPO = Path(__file__).resolve().parents[2]
OWN = REPO / "captures"
REAL = REPO / ".." / "shared" / "captures" / "real"
MBMON = [sys.executable, "-m", "mbmon.cli"]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "TZ": "UTC"}


def mbmon(*args: str | Path, check: bool = True) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(
        [*MBMON, *map(str, args)], capture_output=True, text=True, env=ENV, timeout=600
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    if check:
        assert proc.returncode == 0, proc.stderr
    return proc


def captures() -> Iterator[Path]:
    yield from sorted(OWN.glob("*.pcap"))
    if REAL.is_dir():
        yield from sorted(p for p in REAL.iterdir() if p.suffix in (".pcap", ".pcapng"))


def real(name: str) -> Path:
    path = REAL / name
    if not path.exists():
        pytest.skip(f"{path}: ../shared/captures/real absent")
    return path


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("capture", list(captures()), ids=lambda p: p.name)
def test_replay_json_equals_read_json(tmp_path: Path, capture: Path) -> None:
    log = tmp_path / "x.mcap"
    proc = subprocess.run(
        [*MBMON, "read", str(capture), "--json", "-w", str(log)],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=600,
    )
    assert proc.stdout, proc.stderr
    replayed = mbmon("replay", log, "--json").stdout
    assert replayed.splitlines() == proc.stdout.splitlines()
    with McapLog(log) as opened:
        assert opened.finished  # also when read stopped at damaged input


def test_real_captures_present_or_skipped() -> None:
    if not REAL.is_dir():
        pytest.skip("../shared/captures/real absent")
    assert len([p for p in captures() if p.parent != OWN]) >= 20


@pytest.mark.parametrize(
    "args",
    [
        ["captures/hrss_ptp.pcap", "--profile", "hrss", "--robot", "127.0.0.1:502"],
        ["captures/hrss_rtu.pcap", "--profile", "hrss"],
        ["--rtu-raw", "captures/hrss_rtu.bin", "--profile", "hrss"],
    ],
    ids=["tcp-robot-labels", "rtu-pcap", "rtu-raw"],
)
def test_replay_lines_and_redecode_equal_live(tmp_path: Path, args: list[str]) -> None:
    paths = [str(REPO / a) if a.startswith("captures/") else a for a in args]
    log = tmp_path / "h.mcap"
    live = mbmon("read", *paths).stdout
    live_json = mbmon("read", *paths, "--json", "-w", log).stdout
    assert mbmon("replay", log).stdout == live
    assert mbmon("replay", log, "--redecode").stdout == live
    assert mbmon("replay", log, "--redecode", "--json").stdout == live_json


def test_read_stores_its_analysis_settings(tmp_path: Path) -> None:
    """read -w x.mcap stores --profile, --timeout and --baud as given (keys of the metadata
    record) and replay --redecode uses them: the same lines as live."""
    log = tmp_path / "r.mcap"
    args = ["--rtu-raw", OWN / "hrss_rtu.bin", "--profile", "hrss", "--timeout", "0.3"]
    args += ["--baud", "19200"]
    live = mbmon("read", *args, "-w", log).stdout
    with McapLog(log) as opened:
        meta = opened.metadata["mbmon"]
    assert json.loads(meta["profile_specs"]) == ["hrss"]
    assert (json.loads(meta["timeout"]), json.loads(meta["baud"])) == (0.3, 19200)
    assert json.loads(meta["profile_bindings"]) == [["hrss", 0]]
    assert mbmon("replay", log, "--redecode").stdout == live


def test_sinks_by_suffix_equal_console(tmp_path: Path) -> None:
    capture = OWN / "hrss_ptp.pcap"
    outs = {s: tmp_path / f"o{s}" for s in (".jsonl", ".txt", ".csv", ".pcap", ".mcap")}
    args = [a for p in outs.values() for a in ("-w", p)]
    text = mbmon("read", capture, "--profile", "hrss", *args).stdout
    as_json = mbmon("read", capture, "--profile", "hrss", "--json").stdout
    assert outs[".txt"].read_text("utf-8") == text
    assert outs[".jsonl"].read_text("utf-8") == as_json
    with outs[".csv"].open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    frames = [json.loads(x) for x in as_json.splitlines()]
    assert len(rows) == sum(f["kind"] in ("request", "response", "exception") for f in frames)
    assert (
        mbmon("read", outs[".pcap"], "--profile", "hrss").stdout.splitlines()[1:]
        == (text.splitlines()[1:])
    )  # the handshake time is the connect event's; frames identical


@pytest.mark.parametrize(
    "view", [[], ["--robot", "127.0.0.1:502"]], ids=["neutral-labels", "robot-labels"]
)
def test_jsonl_file_is_read_json_bytes(tmp_path: Path, view: list[str]) -> None:
    """``-w x.jsonl`` holds the bytes ``read --json`` prints, with a profile (notes, state,
    commands) and non-ASCII text (the neutral labels' arrow, degree signs in the notes)."""
    capture = OWN / "hrss_ptp.pcap"
    out = tmp_path / "x.jsonl"
    args = [*MBMON, "read", str(capture), "--profile", "hrss", *view]
    utf8 = {**ENV, "PYTHONIOENCODING": "utf-8"}
    printed = subprocess.run([*args, "--json"], capture_output=True, env=utf8, timeout=600)
    assert printed.returncode == 0, printed.stderr
    written = subprocess.run([*args, "-q", "-w", out], capture_output=True, env=ENV, timeout=600)
    assert written.returncode == 0 and not written.stdout, written.stderr
    assert out.read_bytes() == printed.stdout
    text = printed.stdout.decode("utf-8")
    assert "°" in text and '"command":{' in text and ("→" in text) is (not view)


# --------------------------------------------------------------------------- export


@pytest.mark.parametrize("suffix", [".jsonl", ".txt", ".csv"])
def test_export_text_formats(tmp_path: Path, suffix: str) -> None:
    capture = OWN / "hrss_ptp.pcap"
    log = tmp_path / "h.mcap"
    direct = tmp_path / f"direct{suffix}"
    mbmon("read", capture, "--profile", "hrss", "-q", "-w", log, "-w", direct)
    exported = tmp_path / f"exported{suffix}"
    mbmon("export", log, "-o", exported)
    assert exported.read_bytes() == direct.read_bytes()


EXPORT_TSHARK = [
    "tcp__emreekin__ModbusFloat.pcap",
    "tcp__zeek__modbusSmall.pcap",
    "tcp__ndpi__modbus_fc3_polling.pcap",
    "tcp__yyjccc__modbus_5view_format.pcap",
    "tcp__lemay__send_a_fake_command_6RTU_with_operate.pcap",
]


@pytest.mark.skipif(shutil.which("tshark") is None, reason="tshark not installed")
@pytest.mark.parametrize("name", ["hrss_ptp.pcap", *EXPORT_TSHARK])
def test_export_pcap_agrees_with_tshark(tmp_path: Path, name: str) -> None:
    capture = OWN / name if (OWN / name).exists() else real(name)
    log, out = tmp_path / "x.mcap", tmp_path / "x.pcap"
    frames = [
        json.loads(x) for x in mbmon("read", capture, "--json", "-w", log).stdout.splitlines()
    ]
    mbmon("export", log, "-o", out)
    fields = ["-e", "modbus.func_code", "-e", "modbus.reference_num", "-e", "tcp.analysis.flags"]
    res = subprocess.run(
        ["tshark", "-r", str(out), "-Y", "modbus", "-T", "fields", *fields],
        capture_output=True,
        text=True,
        check=True,
    )
    rows = [line.split("\t") for line in res.stdout.splitlines()]
    fcs = [int(x) for row in rows for x in row[0].split(",") if x]
    assert fcs == [f["fc"] for f in frames if f["kind"] in ("request", "response", "exception")]
    assert not any(row[2] for row in rows), "tshark TCP analysis flags: inconsistent numbering"
    refs = sorted(int(x) for row in rows for x in row[1].split(",") if x)
    requests = sorted(
        f["address"] for f in frames if f["kind"] == "request" and f["address"] is not None
    )
    assert set(requests) <= set(refs)


def test_export_rtu_pcap_reads_back(tmp_path: Path) -> None:
    log, out = tmp_path / "r.mcap", tmp_path / "r.pcap"
    bus = OWN / "hrss_rtu.bin"
    live = [
        json.loads(x)
        for x in mbmon("read", "--rtu-raw", bus, "--json", "-w", log).stdout.splitlines()
    ]
    mbmon("export", log, "-o", out)
    assert out.read_bytes()[20:24] == (147).to_bytes(4, "little")  # link type USER0
    again = [json.loads(x) for x in mbmon("read", out, "--json").stdout.splitlines()]
    key = ("kind", "unit", "fc", "pdu", "address", "count", "values")
    assert [[f[k] for k in key] for f in again] == [[f[k] for k in key] for f in live]


def test_export_repairs_an_unfinished_log(tmp_path: Path) -> None:
    log = tmp_path / "h.mcap"
    mbmon("read", OWN / "hrss_ptp.pcap", "--profile", "hrss", "-q", "-w", log)
    data = log.read_bytes()
    summary_start = int.from_bytes(data[-28:-20], "little")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: summary_start - 5])
    fixed = tmp_path / "fixed.mcap"
    proc = mbmon("export", cut, "-o", fixed)
    assert "not finished" in proc.stderr
    with McapLog(fixed) as opened:
        assert opened.finished and opened.profiles() and opened.metadata["mbmon"]
    assert mbmon("replay", fixed).stdout == mbmon("replay", cut).stdout
    assert mbmon("replay", fixed, "--redecode").stdout == mbmon("replay", log, "--redecode").stdout


def test_export_usage_errors(tmp_path: Path) -> None:
    log = tmp_path / "h.mcap"
    mbmon("read", OWN / "hrss_ptp.pcap", "-q", "-w", log)
    bad = mbmon("export", log, "-o", tmp_path / "x.xlsx", check=False)
    assert bad.returncode == 2 and "unknown output format" in bad.stderr
    bad = mbmon("export", log, "-o", tmp_path / "x.pcap", "--fc", "3", check=False)
    assert bad.returncode == 2 and "--since/--until" in bad.stderr
    bad = mbmon("export", log, "-o", log, check=False)
    assert bad.returncode == 2 and "overwrite" in bad.stderr


# --------------------------------------------------------------------------- replay options


@pytest.fixture(scope="module")
def hrss_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict]]:
    log = tmp_path_factory.mktemp("h") / "h.mcap"
    proc = mbmon("read", OWN / "hrss_ptp.pcap", "--profile", "hrss", "--json", "-w", log)
    return log, [json.loads(x) for x in proc.stdout.splitlines()]


def test_replay_filters(hrss_log: tuple[Path, list[dict]]) -> None:
    log, objs = hrss_log

    def replay(*args: str) -> list[dict]:
        return [json.loads(x) for x in mbmon("replay", log, "--json", *args).stdout.splitlines()]

    assert replay("--fc", "3,0x10") == [o for o in objs if o["fc"] in (3, 16)]
    touching = [
        o
        for o in objs
        if o["address"] is not None
        and o["address"] <= 201
        and o["address"] + max(o["count"] or 1, 1) - 1 >= 200
    ]
    assert replay("--address", "200-201") == touching and touching
    assert replay("--unit", "1", "--fc", "4") == [o for o in objs if o["fc"] == 4]
    assert replay("--unit", "7") == []
    grep = replay("--grep", "ptp")
    assert grep == [o for o in objs if "ptp" in o["line"].lower()] and grep
    t0 = objs[0]["time"]
    window = replay("--since", "+0.1s", "--until", "+0.3s")
    assert window == [o for o in objs if t0 + 0.1 <= o["time"] <= t0 + 0.3] and window
    text = mbmon("replay", log, "--fc", "5").stdout.splitlines()
    assert text == [o["line"] for o in objs if o["fc"] == 5]
    bad = mbmon("replay", log, "--since", "whenever", check=False)
    assert bad.returncode == 2 and "not a time" in bad.stderr
    bad = mbmon("replay", log, "--robot", "1.2.3.4", check=False)
    assert bad.returncode == 2 and "--redecode" in bad.stderr


def test_replay_speed(hrss_log: tuple[Path, list[dict]]) -> None:
    log, objs = hrss_log
    span = objs[-1]["time"] - objs[0]["time"]
    assert span > 0.3

    def timed(speed: str) -> float:
        start = time.monotonic()
        mbmon("replay", log, "--speed", speed)
        return time.monotonic() - start

    # Pacing can only make a replay slower, and a loaded machine only slower still:
    # the lower bound is the property (an upper bound would be a timed test).
    slow = timed("0.5")
    assert slow >= 2 * span * 0.95
    assert timed("1000") < slow


# --------------------------------------------------------------------------- info


def test_info(hrss_log: tuple[Path, list[dict]]) -> None:
    log, objs = hrss_log
    info = json.loads(mbmon("info", log, "--json").stdout)
    assert info["finished"] and info["profiles"] == ["hrss"]
    assert info["profile_attachments"] == ["hrss.toml"]
    frames = [o for o in objs if o["kind"] in ("request", "response", "exception")]
    assert info["topics"]["/modbus/frames"] == len(frames)
    assert info["topics"]["/modbus/monitor"] == len(objs)
    assert sum(fc["total"] for fc in info["function_codes"].values()) == len(frames)
    assert info["exceptions"] == [{"fc": 3, "code": 2, "name": "Illegal Data Address", "count": 1}]
    assert info["commands"]["phases"] == {"written": 1, "executing": 1, "success": 1}
    assert info["commands"]["outcomes"][0]["text"].startswith("PTP")
    assert info["events"] == {"connect": 1, "disconnect": 1}
    assert [s["client"] for s in info["streams"]] == [frames[0]["src"]]
    assert info["start"] <= objs[0]["time"] and info["end"] >= objs[-1]["time"]
    text = mbmon("info", log).stdout
    for needle in ("finished log", "Illegal Data Address", "PTP", "/hrss/state", "hrss.toml"):
        assert needle in text


def test_info_and_replay_of_an_unfinished_log(tmp_path: Path, hrss_log: tuple) -> None:
    log, objs = hrss_log
    data = log.read_bytes()
    summary_start = int.from_bytes(data[-28:-20], "little")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: summary_start - 1])
    info = json.loads(mbmon("info", cut, "--json").stdout)
    assert not info["finished"] and info["recovered_messages"] > 0
    assert info["stopped_at"] is not None
    assert "not finished" in mbmon("info", cut).stdout
    proc = mbmon("replay", cut, "--json")
    assert [json.loads(x) for x in proc.stdout.splitlines()] == objs
    assert "not finished: recovered" in proc.stderr


def test_damaged_and_foreign_logs_fail_cleanly(tmp_path: Path, hrss_log: tuple) -> None:
    log, _ = hrss_log
    data = bytearray(log.read_bytes())
    with open(log, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunk = summary.chunk_indexes[0]
    data[chunk.chunk_start_offset + chunk.chunk_length - 2] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    for cmd in (["replay"], ["info"], ["export", "-o", str(tmp_path / "o.jsonl")]):
        proc = mbmon(*cmd[:1], bad, *cmd[1:], check=False)
        assert proc.returncode == 1 and "chunk at byte" in proc.stderr
    foreign = tmp_path / "f.mcap"
    foreign.write_bytes(b"hello, not a log")
    proc = mbmon("replay", foreign, check=False)
    assert proc.returncode == 1 and "not an MCAP file" in proc.stderr
    proc = mbmon("info", tmp_path / "missing.mcap", check=False)
    assert proc.returncode == 1 and "cannot open" in proc.stderr


def test_info_and_replay_recover_the_same_count(tmp_path: Path, hrss_log: tuple) -> None:
    """Every way of reading a truncated log reports the same recovered count."""
    import re

    log, _ = hrss_log
    data = log.read_bytes()
    summary_start = int.from_bytes(data[-28:-20], "little")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: summary_start - 1])
    n = json.loads(mbmon("info", cut, "--json").stdout)["recovered_messages"]
    assert n > 0
    assert f"recovered {n} messages" in mbmon("info", cut).stdout
    for extra in ([], ["--json"], ["--redecode"], ["--fc", "3"]):
        err = mbmon("replay", cut, *extra).stderr
        assert re.findall(r"recovered (\d+) messages", err) == [str(n)], (extra, err)


def test_logs_without_profiles_have_no_hrss_channels(tmp_path: Path) -> None:
    """No empty /hrss/* channels in a log written without --profile."""
    log = tmp_path / "plain.mcap"
    mbmon("read", OWN / "hrss_ptp.pcap", "-q", "-w", log)
    with open(log, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    topics = {ch.topic for ch in summary.channels.values()}
    assert topics == {"/modbus/raw", "/modbus/frames", "/modbus/monitor", "/mbmon/events"}
    assert all(summary.statistics.channel_message_counts.get(c, 0) for c in summary.channels)
    info = mbmon("info", log).stdout
    assert "/hrss/state" not in info and "/hrss/commands" not in info


def test_captures_and_foreign_files_get_one_clear_line(tmp_path: Path) -> None:
    """A pcap given to a log command suggests mbmon read (usage, exit 2); any
    other file that is not a log is one line (exit 1)."""
    capture = OWN / "hrss_ptp.pcap"
    other = tmp_path / "notes.mcap"
    other.write_bytes(b"just some text\n")
    for cmd in (["info"], ["replay"], ["export", "-o", str(tmp_path / "o.jsonl")]):
        proc = mbmon(cmd[0], capture, *cmd[1:], check=False)
        assert proc.returncode == 2 and proc.stdout == ""
        assert proc.stderr.count("\n") == 1 and f"mbmon read {capture}" in proc.stderr
        proc = mbmon(cmd[0], other, *cmd[1:], check=False)
        assert proc.returncode == 1 and proc.stdout == ""
        assert proc.stderr.count("\n") == 1 and "not an MCAP file" in proc.stderr
    assert not (tmp_path / "o.jsonl").exists()


def test_progress_on_a_terminal_never_takes_stdout(tmp_path: Path) -> None:
    """On a big log, info, replay and export show a progress bar on stderr when
    it is a terminal (a real pty here) and stdout (a file) still gets every line."""
    import pty
    import random

    if "sink_records" not in sys.modules:  # tests/sinks/sink_records.py, by file
        import importlib.util

        spec = importlib.util.spec_from_file_location(
            "sink_records", REPO / "tests" / "sinks" / "sink_records.py"
        )
        assert spec is not None and spec.loader is not None
        sys.modules["sink_records"] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules["sink_records"])
    from sink_records import feed, run_pipeline, session_items

    from mbmon.format import View
    from mbmon.model import Chunk, Direction
    from mbmon.sinks.base import SinkContext
    from mbmon.sinks.mcap import McapSink

    stream = run_pipeline(session_items())
    first = next(x for x in stream if isinstance(x, Chunk))
    rng = random.Random(1)
    log = tmp_path / "big.mcap"
    with McapSink(log, SinkContext(view=View(), source="big")) as sink:
        feed(sink, stream)
        for i in range(500):  # incompressible raw chunks: a log of more than 4 MiB
            sink.on_chunk(Chunk(first.ts + i, first.stream, Direction.C2S, rng.randbytes(12000)))
    assert log.stat().st_size > 5 << 20
    expected = mbmon("replay", log).stdout
    assert expected.count("\n") > 10
    exported = tmp_path / "exported.txt"
    for cmd in (["replay"], ["info"], ["export", "-o", str(exported)]):
        master, slave = pty.openpty()
        out = tmp_path / "out.txt"
        with open(out, "w") as stdout:
            proc = subprocess.Popen([*MBMON, cmd[0], str(log), *cmd[1:]], stdout=stdout,
                                    stderr=slave, env={**ENV, "COLUMNS": "100"})  # fmt: skip
            os.close(slave)
            seen = b""
            while True:
                try:
                    block = os.read(master, 4096)
                except OSError:  # the child closed the terminal
                    break
                if not block:
                    break
                seen += block
            proc.wait(timeout=60)
        os.close(master)
        assert proc.returncode == 0, seen
        assert b"reading big.mcap" in seen, seen
        text = out.read_text()
        if cmd == ["replay"]:
            assert text == expected
        elif cmd == ["info"]:
            assert "finished log" in text and "reading" not in text
        else:
            assert text == "" and exported.read_text() == expected


# --------------------------------------------------------------------------- signals


@pytest.fixture(scope="module")
def long_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Modbus/TCP capture that takes mbmon many seconds to read (25 ADUs per segment)."""
    # 400,000 ADUs: many seconds even on a fast machine
    return write_long_capture(tmp_path_factory.mktemp("big") / "long.pcap", 16000)


def _start_recording(
    capture: Path, log: Path
) -> tuple[subprocess.Popen[str], list, threading.Thread]:
    proc = subprocess.Popen(
        [*MBMON, "read", str(capture), "--json", "-w", str(log)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    received: list[tuple[float, int]] = []

    def reader() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.endswith("\n"):  # a killed process may leave half a line
                received.append((time.monotonic(), json.loads(line)["index"]))

    thread = threading.Thread(target=reader, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not received and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert received, "mbmon read printed nothing"
    return proc, received, thread


def _close_pipes(proc: subprocess.Popen[str], thread: threading.Thread) -> None:
    thread.join(timeout=10)  # the process is gone: the reader sees the end of stdout
    for pipe in (proc.stdout, proc.stderr):
        if pipe is not None:
            pipe.close()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signals_leave_finished_indexed_logs(
    tmp_path: Path, long_capture: Path, sig: signal.Signals
) -> None:
    log = tmp_path / "sig.mcap"
    proc, received, thread = _start_recording(long_capture, log)
    time.sleep(1.0)
    assert proc.poll() is None, "the input must outlast the test"
    proc.send_signal(sig)
    proc.wait(timeout=60)
    assert proc.returncode == 128 + sig
    assert proc.stderr is not None and "Traceback" not in proc.stderr.read()
    _close_pipes(proc, thread)
    with open(log, "rb") as f:
        summary = make_reader(f, validate_crcs=True).get_summary()
    assert summary is not None and summary.chunk_indexes and summary.statistics.message_count
    with McapLog(log) as opened:
        assert opened.finished
        got = [m.json()["line"] for m in opened.messages(["/modbus/monitor"])]
    printed = [i for _, i in received]
    assert got[: len(printed)] == printed  # everything printed was logged


def test_sigkill_keeps_everything_older_than_a_second(tmp_path: Path, long_capture: Path) -> None:
    log = tmp_path / "kill.mcap"
    proc, received, thread = _start_recording(long_capture, log)
    time.sleep(2.0)
    assert proc.poll() is None, "the input must outlast the test"
    killed_at = time.monotonic()
    proc.kill()
    proc.wait(timeout=30)
    _close_pipes(proc, thread)
    # a record printed on stdout was handed to the sinks first (sinks, then console)
    old = {i for t, i in received if t < killed_at - 1.0}
    assert len(old) > 100
    with McapLog(log) as opened:
        assert not opened.finished
        got = [m.json()["line"] for m in opened.messages(["/modbus/monitor"])]
        assert opened.status.messages > 0
    assert old <= set(got), f"lost {len(old - set(got))} records older than one second"
    assert got == list(range(len(got)))
    info = mbmon("info", log).stdout
    assert "log was not finished: recovered" in info and "stopped at byte" in info


def test_signal_statistics_count_what_the_chunks_hold(tmp_path: Path, long_capture: Path) -> None:
    """A recording stopped by SIGINT/SIGTERM at random moments (10 runs) has a
    Statistics record whose per-channel counts and time span are exactly those of a
    linear read of its chunks, and a final stats event that counts the logged records."""
    import random

    rng = random.Random(25)
    for run in range(10):
        log = tmp_path / f"stop{run}.mcap"
        sig = (signal.SIGINT, signal.SIGTERM)[run % 2]
        delay = rng.uniform(0.1, 2.5)
        returncode, err = signal_while_logging(
            long_capture, log, sig, delay, args=["-q"], entry=["-m", "mbmon.cli"], timeout=60
        )
        assert returncode == 128 + sig and "Traceback" not in err, err
        with open(log, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            summary = reader.get_summary()
            assert summary is not None and summary.statistics is not None
            stats = summary.statistics
            topic_of = {cid: ch.topic for cid, ch in summary.channels.items()}
            counted = {topic_of[cid]: n for cid, n in stats.channel_message_counts.items() if n}
            times = []
            read: dict[str, int] = {}
            final = None
            marked = 0  # format 4: frames that stand for their chunk (its message left out)
            for _, channel, msg in reader.iter_messages(log_time_order=False):
                read[channel.topic] = read.get(channel.topic, 0) + 1
                times.append(msg.log_time)
                marked += channel.topic == "/modbus/frames" and msg.data[-6:] in MARKS
                if channel.topic == "/mbmon/events":
                    obj = json.loads(msg.data)
                    if obj["index"] is None and obj["info"].get("final"):
                        final = obj["info"]
        assert counted == read, f"run {run} ({sig.name}): summary {counted}, chunks {read}"
        assert stats.message_count == sum(read.values())
        assert (stats.message_start_time, stats.message_end_time) == (min(times), max(times))
        assert final is not None and final["records"] == read["/modbus/monitor"]
        # every chunk: those stored (and the connection's event) and those left out
        assert final["chunks"] == read.get("/modbus/raw", 0) - 1 + marked


# --------------------------------------------------------------------------- small things


@pytest.mark.parametrize("keep", [8, 200], ids=["magic only", "header cut"])
@pytest.mark.parametrize("suffix", [".mcap", ".csv", ".pcap"])
def test_export_of_a_log_with_nothing_recoverable_writes_nothing(
    tmp_path: Path, keep: int, suffix: str
) -> None:
    log = tmp_path / "h.mcap"
    mbmon("read", OWN / "hrss_ptp.pcap", "-q", "-w", log)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[:keep])
    out = tmp_path / f"out{suffix}"
    proc = mbmon("export", cut, "-o", out, check=False)
    assert proc.returncode == 1
    assert "nothing to export, no file written" in proc.stderr
    assert "recovered 0 messages" in proc.stderr
    assert not out.exists()


def test_replay_q_prints_nothing_but_still_reads_and_reports_the_log(tmp_path: Path) -> None:
    log = tmp_path / "h.mcap"
    mbmon("read", OWN / "hrss_ptp.pcap", "-q", "-w", log)
    assert mbmon("replay", log).stdout  # lines without -q
    quiet = mbmon("replay", log, "-q")
    assert quiet.stdout == "" and quiet.stderr == ""
    assert mbmon("replay", log, "--json", "--quiet").stdout == ""
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int.from_bytes(data[-28:-20], "little") - 5])
    unfinished = mbmon("replay", cut, "-q")
    assert unfinished.stdout == "" and "not finished" in unfinished.stderr
    both = mbmon("replay", log, "-q", "--serve", "127.0.0.1:0", check=False)
    assert both.returncode == 2 and "-q" in both.stderr


def test_info_help_names_no_option_info_does_not_have() -> None:
    text = " ".join(mbmon("info", "--help").stdout.split())
    assert "--since" not in text and "--until" not in text
    for command in ("replay", "export"):  # the commands that have them still say so
        assert "--since/--until accept what it prints" in " ".join(
            mbmon(command, "--help").stdout.split()
        )
