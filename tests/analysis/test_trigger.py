"""Triggers with a pre-trigger buffer (mbmon.analysis.trigger) and the one expression grammar
they share with the display filter (mbmon.filters.parse_expression, ``--where``)."""

from __future__ import annotations

import calendar
import json
import subprocess
import sys
from pathlib import Path

import pytest
from mbmon_cli import mbmon

from mbmon.analysis.trigger import TriggerGate
from mbmon.filters import FilterError, parse_expression
from mbmon.format import View, record_to_json
from mbmon.hub import Hub
from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.pipeline import Pipeline
from mbmon.protocol.mbap import encode_adu
from mbmon.sources.pcapfile import read_capture

REPO = Path(__file__).resolve().parents[2]
START = calendar.timegm((2026, 11, 26, 9, 0, 0))
FAULTS = {600: "exception", 1800: "timeout", 3000: "write"}
EXPR = "exception or timeout or (fc 6 and address 200)"


def faulty(path: Path, faults: dict[int, str] = FAULTS, seconds: int = 3600) -> None:
    """A client polling R0..R1 once a second for an hour; at the given seconds a fault:
    an exception answer, a request never answered, a write of R200."""
    conv = TcpConversation("10.0.0.9:40000", "10.0.0.1:502")
    with PcapWriter(path) as out:
        for frame in conv.open():
            out.write(START, frame)
        for n in range(1, seconds + 1):
            t = START + n
            tid = n & 0xFFFF
            kind = faults.get(n)
            if kind == "write":
                out.write(t, conv.send(True, encode_adu(tid, 1, bytes.fromhex("0600C80001"))))
                out.write(
                    t + 0.005, conv.send(False, encode_adu(tid, 1, bytes.fromhex("0600C80001")))
                )
                continue
            out.write(t, conv.send(True, encode_adu(tid, 1, bytes.fromhex("0300000002"))))
            if kind == "timeout":
                continue
            answer = "8302" if kind == "exception" else "030400010002"
            out.write(t + 0.005, conv.send(False, encode_adu(tid, 1, bytes.fromhex(answer))))
        for frame in conv.close():
            out.write(START + seconds + 1, frame)


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("trig") / "hour.pcap"
    faulty(path)
    return path


def test_an_hour_with_three_faults_gives_three_windows_of_the_right_frames(
    capture: Path, tmp_path: Path
) -> None:
    full = tmp_path / "full.jsonl"
    assert mbmon("read", str(capture), "-q", "-w", str(full)).returncode == 0
    everything = full.read_text().splitlines()
    out = tmp_path / "w"
    out.mkdir()
    run = mbmon(
        "read", str(capture), "--json", "--trigger", EXPR, "--before", "30s", "--after", "10s",
        "-w", str(out / "fault.jsonl"), "-w", str(out / "fault.mcap"),
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    files = sorted(out.glob("fault_*.jsonl"))
    assert len(files) == 3
    assert len(sorted(out.glob("fault_*.mcap"))) == 3
    # the trigger records: the exception at 600 s, the timeout reported 1 s after the
    # request at 1800 s, the write of R200 at 3000 s (its echo, 5 ms later, extends
    # that window by 5 ms); each window from 30 s before to 10 s after
    spans = [(600.005, 610.005), (1801.0, 1811.0), (3000.0, 3010.005)]
    shown = run.stdout.splitlines()
    kept: list[str] = []
    for path, (first, last) in zip(files, spans, strict=True):
        expected = [
            line
            for line in everything
            if START + first - 30 <= json.loads(line)["time"] <= START + last
        ]
        assert path.read_text().splitlines() == expected, path.name
        kept += expected
    assert shown == kept  # shown on stdout: the same windows, nothing else
    assert [json.loads(line)["pdu"] for line in kept].count("83 02") == 1
    assert sum('"event":"timeout"' in line for line in kept) == 1
    assert run.stderr.count("trigger window ") == 3
    assert "(2 triggers; first:" in run.stderr  # the write and its echo: one window
    # every window file is a finished MCAP with the window's frames
    from mcap.reader import make_reader

    for path, expected_file in zip(sorted(out.glob("fault_*.mcap")), files, strict=True):
        with open(path, "rb") as f:
            reader = make_reader(f)
            assert reader.get_summary() is not None
            frames = sum(1 for _s, ch, _m in reader.iter_messages() if ch.topic == "/modbus/frames")
        lines = [json.loads(line) for line in expected_file.read_text().splitlines()]
        assert frames == sum(
            1 for obj in lines if obj["kind"] in ("request", "response", "exception")
        )


def test_window_files_are_named_with_their_start(capture: Path, tmp_path: Path) -> None:
    run = mbmon("read", str(capture), "-q", "--trigger", "timeout", "-w", str(tmp_path / "t.txt"))
    assert run.returncode == 0, run.stderr
    (only,) = tmp_path.glob("t_*.txt")
    assert only.name == "t_00001_20261126T092931Z.txt"  # 09:30:01 - 30 s


def _records(path: Path) -> list:
    return list(Pipeline().run(read_capture(path)))


def test_a_trigger_inside_a_window_extends_it_and_the_buffer_is_bounded(tmp_path: Path) -> None:
    cap = tmp_path / "two.pcap"
    faulty(cap, {100: "exception", 105: "exception", 300: "exception"}, seconds=400)
    got: list = []

    class Keep:
        def on_records(self, records: list) -> None:
            got.extend(records)

    gate = TriggerGate(parse_expression("exception"), 20.0, 10.0, max_held=50)
    gate.add(Keep())
    hub = Hub(Pipeline())
    hub.add_listener(gate)
    hub.run_items(read_capture(cap))
    hub.close()
    assert [
        (w.triggers, round(w.start - START, 3), round(w.end - START, 3)) for w in gate.windows
    ] == [
        (2, 80.005, 115.005),
        (1, 280.005, 310.005),
    ]
    # 50 items held at most: chunks, events and records; so fewer than 20 s before each
    first = [r for r in got if r.ts <= START + 115.005]
    assert min(r.ts for r in first) > START + 80.005
    assert len(got) < 2 * (35 + 30) * 2


# --------------------------------------------------------------------------- the grammar


OBJS = {
    "read": {"kind": "request", "fc": 3, "unit": 1, "address": 0, "count": 2, "values": None},
    "answer": {"kind": "response", "fc": 3, "unit": 1, "address": 0, "count": 2, "values": [1, 2],
               "latency_ms": 5.0},
    "slow": {"kind": "response", "fc": 4, "unit": 2, "address": 300, "count": 2, "values": [7, 0],
             "latency_ms": 80.0},
    "exc": {"kind": "exception", "fc": 3, "unit": 1, "exception_code": 2, "latency_ms": 4.0},
    "write": {"kind": "request", "fc": 6, "unit": 1, "address": 200, "count": None, "values": [1]},
    "zero": {"kind": "request", "fc": 16, "unit": 1, "address": 199, "count": 2, "values": [9, 0]},
    "timeout": {"kind": "event", "event": "timeout"},
    "gone": {"kind": "event", "event": "disconnect"},
    "guard": {"kind": "event", "event": "guard"},
    "crc": {"kind": "noise", "notes": ["noise, 8 bytes (bad CRC)"]},
    "noise": {"kind": "noise", "notes": ["noise, 3 bytes (truncated)"]},
}  # fmt: skip


@pytest.mark.parametrize(
    ("text", "matching"),
    [
        ("exception", {"exc"}),
        ("exception 2", {"exc"}),
        ("exception 3", set()),
        ("timeout", {"timeout"}),
        ("disconnect", {"gone"}),
        ("guard", {"guard"}),
        ("noise", {"crc", "noise"}),
        ("crc", {"crc"}),
        ("fc 6 and address 200", {"write"}),
        ("address 200", {"write", "zero"}),
        ("fc 3,4 and unit 2", {"slow"}),
        ("R200 != 0", {"write"}),
        ("R200 == 0", {"zero"}),
        ("R199>=9", {"zero"}),
        ("IR301 == 0", {"slow"}),
        ("IR300 == 0", set()),
        ("latency > 50ms", {"slow"}),
        ("latency <= 5ms", {"answer", "exc"}),
        ("not (request or response) and not noise", {"exc", "timeout", "gone", "guard"}),
        ("exception or timeout or disconnect", {"exc", "timeout", "gone"}),
        ("response and not fc 4", {"answer"}),
    ],
)
def test_expressions_on_record_objects(text: str, matching: set[str]) -> None:
    expression = parse_expression(text)
    assert {name for name, obj in OBJS.items() if expression.matches(obj)} == matching


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty expression"),
        ("fc", "fc values expected"),
        ("exception or", "a test expected"),
        ("(timeout", "')' expected"),
        ("timeout)", "unexpected ')'"),
        ("R200 ~ 1", "a comparison expected"),
        ("latency > soon", "not a duration"),
        ("reboot", "unknown test 'reboot'"),
        ("address 9-1", "not an address range"),
    ],
)
def test_bad_expressions_say_what_is_wrong(text: str, message: str) -> None:
    with pytest.raises(FilterError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_expression(text)


def test_live_records_and_their_json_objects_agree(capture: Path) -> None:
    """One meaning: an expression says the same of a live record and of its logged object."""
    records = _records(capture)[:1300] + _records(capture)[3550:3650]
    view = View()
    for text in ("exception", "timeout", "fc 6 and address 200", "R0 == 1", "latency > 4ms"):
        expression = parse_expression(text)
        for record in records:
            assert expression.matches_record(record) == expression.matches(
                record_to_json(record, view)
            )


def test_the_display_filter_reads_the_same_grammar(capture: Path) -> None:
    run = mbmon("read", str(capture), "--json", "--where", "exception or timeout")
    assert run.returncode == 0, run.stderr
    kinds = [
        json.loads(line).get("event") or json.loads(line)["kind"]
        for line in run.stdout.splitlines()
    ]
    assert kinds == ["exception", "timeout"]
    bad = mbmon("read", str(capture), "--where", "fc 6 and")
    assert bad.returncode == 2 and "a test expected" in bad.stderr
    bad = mbmon("read", str(capture), "--trigger", "R200 >", "-q")
    assert bad.returncode == 2 and "--trigger:" in bad.stderr
    bad = mbmon("read", str(capture), "--before", "5s", "-q")
    assert bad.returncode == 2 and "--before needs --trigger" in bad.stderr


@pytest.mark.skipif(
    not hasattr(__import__("os"), "geteuid") or __import__("os").geteuid() != 0,
    reason="live capture needs root (an AF_PACKET socket); CI runs as root",
)
def test_sniff_shows_only_the_window_around_a_live_trigger(tmp_path: Path) -> None:
    """``sniff lo --trigger exception --before 1s --after 1s`` while the simulator
    answers reads, one of them with an exception 2.5 s after the others: only that
    exchange is shown and logged."""
    import os
    import select
    import signal
    import socket
    import time

    from mbmon.sim import SimServer

    log = tmp_path / "live.jsonl"
    with SimServer() as sim:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "sniff", "lo", "-f", f"tcp port {sim.port}",
             "--port", str(sim.port), "--json", "--trigger", "exception",
             "--before", "1s", "--after", "1s", "-w", str(log)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO,
        )  # fmt: skip
        try:
            assert proc.stderr is not None and proc.stdout is not None
            assert b"sniffing" in proc.stderr.readline()
            with socket.create_connection((sim.host, sim.port)) as conn:
                for tid, pdu, pause in (
                    (1, "04012C0002", 2.5),
                    (2, "03EA600001", 2.5),
                    (3, "04012C0002", 0),
                ):
                    conn.sendall(encode_adu(tid, 1, bytes.fromhex(pdu)))
                    assert conn.recv(64)
                    time.sleep(pause)
            out = b""
            end = time.monotonic() + 20
            while b'"83 02"' not in out and time.monotonic() < end:
                if select.select([proc.stdout], [], [], 0.5)[0]:
                    out += os.read(proc.stdout.fileno(), 65536)
            time.sleep(1.5)  # the window closes with the next tick
            proc.send_signal(signal.SIGINT)
            rest, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    shown = [json.loads(line) for line in (out + rest).decode().splitlines()]
    assert [(r["kind"], r["pdu"]) for r in shown] == [
        ("request", "03 EA 60 00 01"),
        ("exception", "83 02"),
    ]
    (window_file,) = tmp_path.glob("live_*.jsonl")
    assert [json.loads(line)["pdu"] for line in window_file.read_text().splitlines()] == [
        "03 EA 60 00 01",
        "83 02",
    ]
    assert b"trigger window 1:" in err


def test_replay_and_export_read_the_same_grammar(capture: Path, tmp_path: Path) -> None:
    log = tmp_path / "hour.mcap"
    assert mbmon("read", str(capture), "-q", "-w", str(log)).returncode == 0
    replay = mbmon("replay", str(log), "--json", "--where", "exception or timeout")
    assert replay.returncode == 0, replay.stderr
    assert [
        json.loads(x).get("event") or json.loads(x)["kind"] for x in replay.stdout.splitlines()
    ] == [
        "exception",
        "timeout",
    ]
    out = tmp_path / "writes.jsonl"
    assert mbmon("export", str(log), "-o", str(out), "--where", "R200 != 0").returncode == 0
    assert [json.loads(x)["pdu"] for x in out.read_text().splitlines()] == ["06 00 C8 00 01"] * 2
    refused = mbmon("export", str(log), "-o", str(tmp_path / "x.pcap"), "--where", "timeout")
    assert refused.returncode == 2 and "takes only --since/--until" in refused.stderr
