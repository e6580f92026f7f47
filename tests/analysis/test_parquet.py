"""Parquet logs (mbmon.sinks.parquet): -w and export write the same rows, and DuckDB answers
the queries of docs/fleet.md (run as the page shows them) over a folder of cells' files."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mbmon_cli import mbmon

from mbmon.io.pcap import PcapWriter, TcpConversation
from mbmon.protocol.mbap import encode_adu

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
duckdb = pytest.importorskip("duckdb")

REPO = Path(__file__).resolve().parents[2]
FLEET_DOC = REPO / "docs" / "fleet.md"
DAY = 86400.0


def cell(
    path: Path,
    robot: str,
    start: float,
    latencies_ms: list[float | None],
    *,
    exceptions: frozenset[int] = frozenset(),
    every: float = 1.0,
) -> None:
    """One client polling ``robot``: poll n answered after ``latencies_ms[n]`` ms
    (``None``: never answered: a timeout), an exception when n is in ``exceptions``."""
    conv = TcpConversation("10.9.9.9:40000", robot)
    with PcapWriter(path) as out:
        for frame in conv.open():
            out.write(start, frame)
        t = start
        for n, latency in enumerate(latencies_ms):
            t = start + 1 + n * every
            tid = n + 1
            out.write(t, conv.send(True, encode_adu(tid, 1, bytes.fromhex("0300000002"))))
            if latency is not None:
                answer = "8302" if n in exceptions else "030400010002"
                out.write(
                    t + latency / 1000, conv.send(False, encode_adu(tid, 1, bytes.fromhex(answer)))
                )
        for frame in conv.close():
            out.write(t + 5, frame)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three cells' logs in ``fleet/``: cell01 by ``read -w``, cell02 by ``export`` of an
    MCAP log, cell03 (ten days old) rotated hourly."""
    root = tmp_path_factory.mktemp("plant")
    folder = root / "fleet"
    folder.mkdir()
    now = time.time()
    # cell01: 100 answers of 1..100 ms and 3 timeouts, two days ago
    lat1: list[float | None] = [float(ms) for ms in range(1, 101)]
    for at in (10, 50, 90):
        lat1.insert(at, None)
    cell(root / "c1.pcap", "10.0.1.1:502", now - 2 * DAY, lat1)
    assert (
        mbmon("read", str(root / "c1.pcap"), "-q", "-w", str(folder / "cell01.parquet")).returncode
        == 0
    )
    # cell02: 50 polls, answers of 12 ms (2 exceptions) and 1 timeout, three days ago
    lat2: list[float | None] = [12.0] * 50
    lat2[20] = None
    cell(root / "c2.pcap", "10.0.2.1:502", now - 3 * DAY, lat2, exceptions=frozenset({5, 30}))
    assert (
        mbmon("read", str(root / "c2.pcap"), "-q", "-w", str(root / "cell02.mcap")).returncode == 0
    )
    run = mbmon("export", str(root / "cell02.mcap"), "-o", str(folder / "cell02.parquet"))
    assert run.returncode == 0, run.stderr
    # cell03: 20 polls every 10 min (15 answers of 30 ms, 5 timeouts), ten days ago, hourly files
    lat3: list[float | None] = [30.0] * 15 + [None] * 5
    cell(root / "c3.pcap", "10.0.3.1:502", now - 10 * DAY, lat3, every=600.0)
    run = mbmon(
        "read", str(root / "c3.pcap"), "-q", "-w", str(folder / "cell03.parquet"), "--rotate", "1h"
    )
    assert run.returncode == 0, run.stderr
    assert len(list(folder.glob("cell03_*.parquet"))) >= 3
    return root


def doc_queries() -> list[str]:
    return re.findall(r"```sql\n(.*?)```", FLEET_DOC.read_text(), re.S)


def test_the_queries_of_fleet_md_give_the_expected_numbers(
    fleet: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(fleet)
    most_timeouts, p99, exceptions = doc_queries()
    # cell03's five timeouts are ten days old: not last week
    assert duckdb.sql(most_timeouts).fetchall() == [("10.0.1.1:502", 3), ("10.0.2.1:502", 1)]
    # 1..100 ms: p99 by linear interpolation 99.01; exceptions are answers too
    assert duckdb.sql(p99).fetchall() == [
        ("cell01", 100, 99.01),
        ("cell02", 49, 12.0),
        ("cell03", 15, 30.0),
    ]
    assert duckdb.sql(exceptions).fetchall() == [("10.0.2.1:502", 3, 2, 2)]


def test_write_and_export_give_the_same_rows(fleet: Path, tmp_path: Path) -> None:
    direct = tmp_path / "direct.parquet"
    assert mbmon("read", str(fleet / "c2.pcap"), "-q", "-w", str(direct)).returncode == 0
    a = pq.read_table(direct)
    b = pq.read_table(fleet / "fleet" / "cell02.parquet")
    assert (
        a.num_rows == b.num_rows == 50 + 49 + 1 + 2
    )  # requests, answers, timeout, connect+disconnect
    assert a.equals(b)
    meta = json.loads(a.schema.metadata[b"mbmon"])
    assert meta["source"].endswith("c2.pcap") and meta["timeout"] == 1.0
    raws = [r for r in a.column("raw").to_pylist() if r is not None]
    assert raws[0] == encode_adu(1, 1, bytes.fromhex("0300000002"))
    assert str(a.schema.field("time").type) == "timestamp[us, tz=UTC]"


def test_rotated_parquet_counts_equal_one_file(fleet: Path, tmp_path: Path) -> None:
    one = tmp_path / "one.parquet"
    assert mbmon("read", str(fleet / "c3.pcap"), "-q", "-w", str(one)).returncode == 0
    parts = sorted((fleet / "fleet").glob("cell03_*.parquet"))
    assert sum(pq.read_table(p).num_rows for p in parts) == pq.read_table(one).num_rows


def test_without_pyarrow_the_message_names_the_pip_command(tmp_path: Path, fleet: Path) -> None:
    out = tmp_path / "x.parquet"
    code = (
        "import sys; sys.modules['pyarrow'] = None; from mbmon.cli import main; "
        f"sys.exit(main(['read', {str(fleet / 'c2.pcap')!r}, '-q', '-w', {str(out)!r}]))"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120
    )
    assert run.returncode == 1
    assert "pip install 'mbmon[parquet]'" in run.stderr and "Traceback" not in run.stderr
    assert not out.exists()
