"""``mbmon report`` (mbmon.analysis.report): figures against captures built with known
periods, latencies and faults; tables on the terminal; a self-contained HTML page that
headless Chromium opens with every picture shown."""

from __future__ import annotations

import base64
import calendar
import re
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import pytest
from mbmon_cli import mbmon

from mbmon.analysis.report import analyse, percentile, text_tables
from mbmon.format import View, record_to_json
from mbmon.io import pcap as pw
from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.protocol.crc import add_crc
from mbmon.protocol.mbap import encode_adu
from mbmon.sources.pcapfile import read_capture

REPO = Path(__file__).resolve().parents[2]
START = calendar.timegm((2026, 11, 26, 8, 0, 0))
SKIPPED = {100, 200, 201}  # polls of block A that never happen: 1 + 2 missed cycles
EXCEPTIONS = {50, 400}  # polls of block A answered with exception 02
UNANSWERED = {300}  # a poll of block A never answered


def known(path: Path) -> None:
    """One client, two blocks on one connection for 60 s: block A (R0..R1) every 100 ms
    answered in 5 ms, block B (IR300..IR309) every 250 ms answered in 20 ms."""
    conv = TcpConversation("10.0.0.9:40000", "10.0.0.1:502")
    sends: list[tuple[float, bool, bytes]] = []
    tid = 0
    for n in range(600):
        if n in SKIPPED:
            continue
        tid += 1
        t = START + 1 + n * 0.1
        sends.append((t, True, encode_adu(tid, 1, bytes.fromhex("0300000002"))))
        if n in UNANSWERED:
            continue
        answer = "8302" if n in EXCEPTIONS else "030400010002"
        sends.append((t + 0.005, False, encode_adu(tid, 1, bytes.fromhex(answer))))
    for n in range(240):
        tid += 1
        t = START + 1.03 + n * 0.25
        sends.append((t, True, encode_adu(tid, 1, bytes.fromhex("04012C000A"))))
        sends.append((t + 0.020, False, encode_adu(tid, 1, bytes.fromhex("0414" + "0001" * 10))))
    sends.sort(key=lambda s: s[0])
    with PcapWriter(path) as out:
        for frame in conv.open():
            out.write(START, frame)
        for t, from_client, payload in sends:
            out.write(t, conv.send(from_client, payload))
        for frame in conv.close():
            out.write(START + 62, frame)


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("report") / "known.pcap"
    known(path)
    return path


def objects(path: Path, baud: int | None = None) -> list[dict]:
    view = View()
    pipeline = Pipeline(config=PipelineConfig(baudrate=baud))
    return [record_to_json(r, view) for r in pipeline.run(read_capture(path))]


def test_figures_of_a_capture_with_known_periods_latencies_and_faults(capture: Path) -> None:
    fig = analyse(objects(capture), source="known.pcap")
    a, b = fig.blocks
    assert (a.fc, a.address, a.count, b.fc, b.address, b.count) == (3, 0, 2, 4, 300, 10)
    assert len(a.times) == 597 and len(b.times) == 240
    assert a.period == pytest.approx(0.1) and b.period == pytest.approx(0.25)
    assert a.missed == 3 and b.missed == 0
    assert b.jitter == pytest.approx(0.0, abs=1e-6)
    # 596 intervals: 594 of 100 ms, one of 200 ms and one of 300 ms (the skipped polls)
    assert a.jitter == pytest.approx(statistics.pstdev([0.1] * 594 + [0.2, 0.3]), rel=1e-6)
    assert percentile(a.latencies_ms, 50) == pytest.approx(5.0)
    assert percentile(b.latencies_ms, 99) == pytest.approx(20.0)
    assert (a.exceptions, a.timeouts, b.exceptions, b.timeouts) == (2, 1, 0, 0)
    assert (fig.exceptions, fig.timeouts) == (2, 1)
    times = sorted(round(ts - START, 3) for ts, _, _ in fig.faults)
    assert times == [6.005, 32.0, 41.005]  # exceptions at polls 50 and 400, timeout of 300
    assert percentile(fig.latencies_ms, 50) == pytest.approx(5.0)
    assert max(fig.latencies_ms) == pytest.approx(20.0)


def test_percentile_interpolates_like_numpy() -> None:
    assert percentile([1, 2, 3, 4], 50) == 2.5
    assert percentile([10.0], 99) == 10.0
    assert percentile([1, 2, 3, 4, 5], 95) == pytest.approx(4.8)


def test_damaged_records_give_figures_without_times_not_a_crash() -> None:
    """Records read from a damaged log: a time that is no number and a timeout whose
    request index is no number are kept without a time (the timeline leaves them
    out) instead of a time that cannot be drawn or an unhashable lookup."""
    fig = analyse(
        [
            {"kind": "request", "time": 1.0, "index": 0, "src": "c:1", "dst": "s:502", "fc": 3},
            {"kind": "exception", "time": "noon", "src": "s:502", "dst": "c:1", "fc": 3},
            {"kind": "event", "event": "timeout", "time": [2], "info": {"request_index": [0]}},
            {"kind": "command", "time": "x", "command": {"text": "PTP", "phase": "written"}},
        ]
    )
    assert (fig.first, fig.last, fig.records) == (1.0, 1.0, 4)
    assert [(ts, kind) for ts, kind, _ in fig.faults] == [(None, "exception"), (None, "timeout")]
    assert fig.commands == [(None, "PTP", "written")]
    assert "faults: 1 exceptions, 1 timeouts" in text_tables(fig)


def test_terminal_tables_without_output(capture: Path) -> None:
    run = mbmon("report", str(capture))
    assert run.returncode == 0, run.stderr
    rows = {line.split()[6]: line.split() for line in run.stdout.splitlines() if "u1 fc" in line}
    # block, requests, period, jitter, missed, p50 p95 p99 max, exceptions, timeouts
    assert rows["0..1"][7:] == ["597", "100.0", "9.1", "3", "5.0", "5.0", "5.0", "5.0", "2", "1"]
    assert rows["300..309"][7:] == [
        "240",
        "250.0",
        "0.0",
        "0",
        "20.0",
        "20.0",
        "20.0",
        "20.0",
        "0",
        "0",
    ]
    assert "faults: 2 exceptions, 1 timeouts" in run.stdout


def test_rtu_bus_health(tmp_path: Path) -> None:
    """A bus at 19200 baud: a request every 100 ms, its answer 20 ms later, one answer
    with a bad CRC."""
    path = tmp_path / "bus.pcap"
    request = add_crc(bytes.fromhex("110300000002"))
    answer = add_crc(bytes.fromhex("1103040001000A"))
    with PcapWriter(path, pw.LINKTYPE_USER0) as out:
        for n in range(50):
            t = START + n * 0.1
            out.write(t, request)
            bad = n == 10
            out.write(t + 0.02, answer[:-1] + bytes([answer[-1] ^ 0xFF]) if bad else answer)
    fig = analyse(objects(path, baud=19200), source="bus.pcap", baud=19200)
    (bus,) = fig.buses
    # the bad answer is one noise run with a bad CRC: counted as the summary counts them
    assert bus.crc_errors == 1 and bus.frames == 99
    # silence after a request (8 bytes) before its 9-byte answer: 20 ms less 9*11/19200 s
    assert min(bus.gaps_ms) == pytest.approx(20.0 - 9 * 11 / 19.2, abs=0.01)
    text = text_tables(fig)
    assert "RTU bus health" in text and "CRC errors" in text


def test_html_is_self_contained_with_every_picture(capture: Path, tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    page = tmp_path / "report.html"
    pngs = tmp_path / "png"
    run = mbmon("report", str(capture), "-o", str(page), "--png", str(pngs))
    assert run.returncode == 0, run.stderr
    text = page.read_text()
    images = re.findall(r'<img alt="([^"]+)" src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert [alt for alt, _ in images] == [
        "Poll cycle per client and register block",
        "Latency histogram and percentiles",
        "Exceptions and timeouts on a timeline",
    ]
    for _alt, data in images:
        assert base64.b64decode(data)[:8] == b"\x89PNG\r\n\x1a\n"
    assert "http://" not in text and "https://" not in text and "<script" not in text
    assert sorted(p.name for p in pngs.iterdir()) == [
        "faults.png",
        "latency.png",
        "poll_cycles.png",
    ]


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


@pytest.mark.skipif(_chromium() is None, reason="no Chromium: apt-get install -y chromium")
def test_the_page_opens_in_headless_chromium_with_every_figure(
    capture: Path, tmp_path: Path
) -> None:
    """Chromium loads the page offline; a copy with a probe script reports how many
    images decoded (natural size > 0); a screenshot is kept with the test's files."""
    pytest.importorskip("matplotlib")
    page = tmp_path / "report.html"
    assert mbmon("report", str(capture), "-o", str(page)).returncode == 0
    probe = tmp_path / "probe.html"
    probe.write_text(
        page.read_text().replace(
            "</body>",
            "<script>window.addEventListener('load', () => { const i = [...document.images];"
            " document.body.insertAdjacentHTML('beforeend', '<p id=probe>' + i.length + ' images, '"
            " + i.filter(x => x.complete && x.naturalWidth > 0).length + ' shown</p>'); });"
            "</script></body>",
        )
    )
    chromium = _chromium()
    assert chromium is not None
    base = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
            f"--user-data-dir={tmp_path / 'profile'}"]  # fmt: skip
    dom = subprocess.run(
        [*base, "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert "3 images, 3 shown" in dom.stdout, dom.stderr[-2000:]
    shot = tmp_path / "report-screenshot.png"
    subprocess.run(
        [*base, f"--screenshot={shot}", "--window-size=1200,2400", page.as_uri()],
        capture_output=True, timeout=120,
    )  # fmt: skip
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and shot.stat().st_size > 20_000


def test_without_matplotlib_the_message_names_the_pip_command(
    capture: Path, tmp_path: Path
) -> None:
    code = (
        "import sys; sys.modules['matplotlib'] = None; from mbmon.cli import main; "
        f"sys.exit(main(['report', {str(capture)!r}, '-o', {str(tmp_path / 'r.html')!r}]))"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120
    )
    assert run.returncode == 1
    assert "pip install 'mbmon[report]'" in run.stderr and "Traceback" not in run.stderr
    assert not (tmp_path / "r.html").exists()


def test_commands_and_outcomes_with_a_profile() -> None:
    """The project's own capture of the HRSS program: one PTP command, its outcome."""
    from mbmon.semantics.annotate import annotator_for

    capture = REPO / "captures" / "hrss_ptp.pcap"
    view = View()
    pipeline = Pipeline(annotator_for(["hrss"]))
    objs = [record_to_json(r, view) for r in pipeline.run(read_capture(capture))]
    fig = analyse(objs, source=capture.name)
    assert [(text.split()[0], outcome) for _, text, outcome in fig.commands] == [
        ("PTP", "success after 0.405 s")
    ]
    assert "success after 0.405 s" in text_tables(fig)
