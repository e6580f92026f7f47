"""``read -w x.mcap`` on the core against the reference pipeline: the same messages
(topic, sequence, times, payload), the same summary, metadata and console, on every
capture the project and others made and on generated ones; a declined input never
opens the log; the log reads back alike through ``info``, ``replay`` and ``export``;
a recording killed mid-way stays readable."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from core_diff import REAL, ROOT, require_core
from gen import T0, adus, every_function_pair, write_conversation, write_frames
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap_diff import assert_same_log, core_log, log_contents

from mbmon.io.mcap.reader import McapLog
from mbmon.io.pcap import TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response

OWN = sorted((ROOT / "captures").glob("*.pcap*"))
PUBLIC = sorted(REAL.glob("*.pcap*")) if REAL.is_dir() else []
COVERED = {"demo.pcap", "hrss_ptp.pcap", "sim_exceptions.pcap", "sim_functions.pcap"}
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "TZ": "UTC"}


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


@pytest.mark.parametrize("path", OWN, ids=lambda p: p.name)
def test_own_captures(path: Path, tmp_path: Path) -> None:
    assert_same_log(path, tmp_path, covered=True if path.name in COVERED else None)


@pytest.mark.parametrize("path", PUBLIC, ids=lambda p: p.name)
def test_public_captures(path: Path, tmp_path: Path) -> None:
    assert_same_log(path, tmp_path)


def test_public_captures_present(tmp_path: Path) -> None:
    if not PUBLIC:
        pytest.skip(f"{REAL} absent (../shared/captures/real)")
    covered = []
    for p in PUBLIC:
        (tmp_path / p.stem).mkdir()
        if assert_same_log(p, tmp_path / p.stem) is None:
            covered.append(p)
    assert len(covered) >= len(PUBLIC) // 2, "the core declined most real captures"


def test_every_function_code_and_ends(tmp_path: Path) -> None:
    pairs = every_function_pair()
    fc = write_conversation(tmp_path / "fc.pcap", adus(pairs))
    assert_same_log(fc, tmp_path, covered=True)
    mid = write_conversation(tmp_path / "mid.pcap", adus(pairs), handshake=False, close="rst")
    assert_same_log(mid, tmp_path, covered=True)
    still_open = write_conversation(tmp_path / "open.pcap", adus(pairs[:3]), close=None)
    assert_same_log(still_open, tmp_path, covered=True)


@pytest.mark.parametrize(
    ("linktype", "pcapng", "vlans"),
    [(1, False, ()), (1, True, ((0x88A8, 1), (0x8100, 2))), (113, False, ()), (108, True, ())],
)
def test_link_types(tmp_path: Path, linktype: int, pcapng: bool, vlans: tuple) -> None:
    path = write_conversation(
        tmp_path / "link.pcapng",
        adus(every_function_pair()[:6]),
        linktype=linktype,
        pcapng=pcapng,
        vlans=vlans,
    )
    assert_same_log(path, tmp_path, covered=True)


def test_mixed_segments_and_splits(tmp_path: Path) -> None:
    stream = adus(every_function_pair())
    requests = b"".join(a for c, a in stream if c)
    answers = b"".join(a for c, a in stream if not c)
    path = write_conversation(tmp_path / "mixed.pcap", [(True, requests), (False, answers)])
    assert_same_log(path, tmp_path, covered=True)
    req = encode_adu(7, 1, encode_read_request(3, 10, 4))
    resp = encode_adu(7, 1, encode_read_response(3, [1, 2, 3, 4]))
    both = req + encode_adu(8, 1, encode_read_request(4, 0, 1))
    for cut in range(1, len(both)):
        split = tmp_path / f"split{cut}.pcap"
        write_conversation(split, [(True, both[:cut]), (False, resp), (True, both[cut:])])
        assert_same_log(split, tmp_path, covered=True)


def test_retransmission_and_overlap(tmp_path: Path) -> None:
    """A chunk is logged as delivered: a retransmission not at all, an overlap's new
    bytes only."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    req = encode_adu(1, 1, encode_read_request(3, 0, 2))
    req2 = encode_adu(2, 1, encode_read_request(3, 2, 2))
    seq = conv.client_next
    frames.append(conv.send(True, req))
    frames.append(conv.segment(True, 0x18, req, seq=seq, advance=False))
    frames.append(conv.segment(True, 0x18, req[-3:] + req2, seq=seq + len(req) - 3))
    conv.client_next = (seq + len(req) + len(req2)) & 0xFFFFFFFF
    frames.append(conv.send(False, encode_adu(1, 1, encode_read_response(3, [1, 2]))))
    frames.append(conv.send(False, encode_adu(2, 1, encode_read_response(3, [3, 4]))))
    frames += conv.close(False)
    path = write_frames(tmp_path / "rtx.pcap", [(T0 + i * 0.01, f) for i, f in enumerate(frames)])
    assert_same_log(path, tmp_path, covered=True)


def test_timeouts_late_answers_and_stats_events(tmp_path: Path) -> None:
    """Timeouts (events, the layout's way), an unsolicited answer (a warning on the
    monitor), and a span of minutes: a stats event every 10 s of capture time lands
    at the frame record where it is due, between frames the core writes itself."""
    req = encode_adu(1, 1, encode_read_request(3, 0, 2))
    answer = encode_adu(1, 1, encode_read_response(3, [1, 2]))
    segments = [(True, req), (True, req), (False, answer)]
    for tid in range(2, 200):
        segments.append((True, encode_adu(tid, 1, encode_read_request(3, tid, 2))))
        if tid % 7:
            segments.append((False, encode_adu(tid, 1, encode_read_response(3, [tid, 1]))))
    times = [T0 + 0.37 * i for i in range(len(segments) + 8)]
    path = write_conversation(tmp_path / "long.pcap", segments, times=times)
    assert_same_log(path, tmp_path, covered=True)
    assert_same_log(path, tmp_path, covered=True, timeout=0.1)
    contents = log_contents(tmp_path / "core0.mcap")
    stats = [m for m in contents["messages"] if m[0] == "/mbmon/events" and b'"stats"' in m[4]]
    assert len(stats) > 5  # due ones and the final one


@pytest.mark.parametrize(
    "times",
    [
        [T0 - i for i in range(20)],  # backwards
        [0.0] * 20,  # the epoch: a log time MCAP clamps to 0
        [4294967295.0 - 10 + i * 0.3 for i in range(20)],  # the last second pcap holds
        [T0 + (86400 * 3 if i > 8 else 0) + i for i in range(20)],  # days apart
    ],
    ids=["backwards", "epoch", "end-of-pcap-time", "days"],
)
def test_impossible_timestamps(tmp_path: Path, times: list[float]) -> None:
    path = write_conversation(tmp_path / "time.pcap", adus(every_function_pair()[:6]), times=times)
    assert_same_log(path, tmp_path, covered=True)


def _pieces(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in itertools.pairwise(points) if b > a]


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    client_cuts=st.lists(st.integers(0, 10_000), max_size=30),
    server_cuts=st.lists(st.integers(0, 10_000), max_size=30),
    gap=st.sampled_from([0.0005, 0.3, 1.5]),
)
def test_random_segmentations(client_cuts: list[int], server_cuts: list[int], gap: float) -> None:
    stream = adus(every_function_pair())
    cs = _pieces(b"".join(a for c, a in stream if c), client_cuts)
    ss = _pieces(b"".join(a for c, a in stream if not c), server_cuts)
    segments: list[tuple[bool, bytes]] = []
    while cs or ss:
        if cs:
            segments.append((True, cs.pop(0)))
        if ss:
            segments.append((False, ss.pop(0)))
    with tempfile.TemporaryDirectory() as tmp:
        path = write_conversation(Path(tmp) / "r.pcap", segments, step=gap)
        assert_same_log(path, Path(tmp), covered=True)


def test_a_declined_input_never_touches_the_log(tmp_path: Path) -> None:
    """Noise alone, a damaged capture: the core declines before opening the log; a file
    already there keeps its bytes (the reference pipeline is the one to write it)."""
    noise = write_conversation(tmp_path / "noise.pcap", [(True, b"\x01\x02\x03garbage!" * 3)])
    log = tmp_path / "x.mcap"
    log.write_bytes(b"before")
    _, _, why = core_log(noise, log)
    assert why is not None and log.read_bytes() == b"before"
    # (a hole is the core's now, tests/core/test_core_net_tcp.py): a damaged capture
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    frames.append(conv.send(True, encode_adu(1, 1, encode_read_request(3, 0, 2))))
    cut = write_frames(tmp_path / "cut.pcap", [(T0 + i, f) for i, f in enumerate(frames)])
    cut.write_bytes(cut.read_bytes()[:-3])
    assert assert_same_log(cut, tmp_path, covered=False)


def _mbmon(*args: str, pure: bool = False) -> subprocess.CompletedProcess[str]:
    env = {**ENV, "MBMON_NO_EXTENSIONS": "1"} if pure else ENV
    return subprocess.run(
        [sys.executable, "-m", "mbmon", *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=600,
        check=False,
    )


def test_the_commands_that_read_logs_see_no_difference(tmp_path: Path) -> None:
    """``read -w`` on the core and forced pure, then ``info``, ``replay``,
    ``replay --redecode --json`` and ``export`` of each: the same output."""
    capture = ROOT / "captures" / "hrss_ptp.pcap"
    logs = {}
    for pure in (False, True):
        log = tmp_path / f"{'pure' if pure else 'core'}.mcap"
        done = _mbmon("read", str(capture), "-w", str(log), "--debug-core", pure=pure)
        assert done.returncode == 0, done.stderr
        ran = "compiled core read the input" in done.stderr
        assert ran is not pure, done.stderr
        logs[pure] = log
    for args in (["info"], ["replay"], ["replay", "--redecode", "--json"]):
        outs = [_mbmon(*args, str(logs[pure])) for pure in (False, True)]
        assert outs[0].returncode == outs[1].returncode == 0, (args, outs[0].stderr)
        texts = [
            "\n".join(
                ln.replace(str(logs[pure]), "LOG")
                for ln in out.stdout.splitlines()
                if "recorded by" not in ln and not ln.startswith("file:")  # its size: chunking
            )
            for out, pure in zip(outs, (False, True), strict=True)
        ]
        assert texts[0] == texts[1], args
    exported = []
    for pure in (False, True):
        out = tmp_path / f"export{int(pure)}.jsonl"
        done = _mbmon("export", str(logs[pure]), "-o", str(out))
        assert done.returncode == 0, done.stderr
        exported.append(out.read_bytes())
    assert exported[0] == exported[1] and exported[0]


def test_a_killed_recording_stays_readable(tmp_path: Path) -> None:
    """SIGKILL while the core writes the log: every chunk on disk reads back (the
    reader's linear recovery), frames and their monitor lines in order."""
    from long_capture import write_long_capture

    capture = write_long_capture(tmp_path / "long.pcap", 12000)
    log = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "read", str(capture), "-q", "-w", str(log)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=ENV,
    )
    deadline = time.monotonic() + 120
    while (not log.exists() or log.stat().st_size < 3_000_000) and time.monotonic() < deadline:
        if proc.poll() is not None:
            break
        time.sleep(0.005)
    assert proc.poll() is None, "the run must outlast the test"
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=60)
    with McapLog(log) as opened:
        assert not opened.finished
        topics = [m.topic for m in opened.messages(["/modbus/frames", "/modbus/monitor"])]
    assert (
        len(topics) > 1000 and topics.count("/modbus/frames") >= topics.count("/modbus/monitor") - 1
    )


def test_which_logs_the_core_writes(tmp_path: Path) -> None:
    """One ``.mcap`` log (any case of the suffix), quiet or not: the core; two logs or
    another format: the Python pipeline, which names the reason; a log that cannot be
    opened: the same error and exit status either way."""
    demo = str(ROOT / "captures" / "demo.pcap")
    for args in (["-q", "-w", str(tmp_path / "a.mcap")], ["-w", str(tmp_path / "B.MCAP")]):
        done = _mbmon("read", demo, *args, "--debug-core")
        assert done.returncode == 0 and "compiled core read the input" in done.stderr, args
    for args in (
        ["-w", str(tmp_path / "c.jsonl")],
        ["-w", str(tmp_path / "d.mcap"), "-w", str(tmp_path / "e.mcap")],
    ):
        done = _mbmon("read", demo, "-q", *args, "--debug-core")
        assert done.returncode == 0, done.stderr
        assert "declined (-w other than one .mcap log" in done.stderr, args
    bad = str(tmp_path / "missing" / "x.mcap")
    core, pure = (_mbmon("read", demo, "-q", "-w", bad, pure=p) for p in (False, True))
    assert core.returncode == pure.returncode == 1
    assert core.stderr == pure.stderr and "cannot write" in core.stderr
