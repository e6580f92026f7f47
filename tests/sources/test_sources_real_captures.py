"""The reader on real public captures, and byte counts checked against tshark."""

from __future__ import annotations

import collections
import shutil
import subprocess
from pathlib import Path

import pytest

from mbmon.model import Chunk, Event, EventKind, Transport
from mbmon.sources.pcapfile import read_capture

REAL = Path(__file__).resolve().parents[2] / ".." / "shared" / "captures" / "real"
TSHARK = shutil.which("tshark")
FILES = sorted(p.name for p in REAL.glob("*.pcap*")) if REAL.is_dir() else []

# tshark differential: files where tshark's view of the TCP streams is sound (the
# zeek fuzz files carry garbage sequence numbers on which any two reassemblers
# disagree by policy, so they are excluded from the byte comparison only).
DIFFERENTIAL = [
    "tcp__iti__ModbusTCP_plant_cloudshark.pcap",  # 14 connections, 8 retransmissions
    "tcp__digitalbond__modbus_test_data_part2.pcap",  # retransmissions
    "tcp__zeek__modbusBig.pcap",  # retransmission + an unseen acknowledged segment
    "tcp__lemay__send_a_fake_command_6RTU_with_operate.pcap",  # 1233 connections
    "tcp__emreekin__crash.pcap",  # RST then a new SYN on the same addresses
    "tcp__zeek__fuzz-1011.pcap",  # holes acknowledged by the peer
]


def _require_real() -> None:
    if not REAL.is_dir():
        pytest.skip(f"{REAL} absent (../shared/captures/real)")


@pytest.mark.parametrize("name", FILES or ["<none>"])
def test_every_real_capture_reads_without_error(name: str) -> None:
    _require_real()
    stats: dict[str, int] = {}
    items = list(read_capture(REAL / name, stats=stats))
    assert not [i for i in items if isinstance(i, Event) and i.kind is EventKind.ERROR]
    chunks = [i for i in items if isinstance(i, Chunk)]
    assert chunks, "every file holds Modbus/TCP payload"
    assert {c.stream.transport for c in chunks} == {Transport.TCP}
    assert stats["packets"] > 0
    # stream ids are dense, in order of first appearance
    first_seen = list(dict.fromkeys(i.stream.id for i in items if i.stream is not None))
    assert first_seen == sorted(first_seen)
    assert set(first_seen) == set(range(stats["streams"]))


def test_5view_file_matches_tshark_packet_count() -> None:
    _require_real()
    stats: dict[str, int] = {}
    list(read_capture(REAL / "tcp__yyjccc__modbus_5view_format.pcap", stats=stats))
    assert stats["packets"] == 1410  # capinfos / SOURCES.md


def _tshark_bytes(path: Path) -> collections.Counter[tuple[int, str]]:
    """Per Modbus TCP connection (renumbered in order of appearance) and direction,
    tshark's payload bytes without the segments it calls retransmissions."""
    assert TSHARK is not None
    result = subprocess.run(
        [
            TSHARK,
            "-r",
            str(path),
            "-Y",
            "tcp.port == 502 && !tcp.analysis.retransmission",
            "-T",
            "fields",
            "-e",
            "tcp.stream",
            "-e",
            "tcp.dstport",
            "-e",
            "tcp.len",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    order: dict[str, int] = {}
    counts: collections.Counter[tuple[int, str]] = collections.Counter()
    for line in result.stdout.splitlines():
        stream, dport, length = line.split("\t")
        sid = order.setdefault(stream, len(order))
        counts[(sid, "c2s" if dport == "502" else "s2c")] += int(length)
    return +counts


@pytest.mark.skipif(TSHARK is None, reason="tshark not installed")
@pytest.mark.parametrize("name", DIFFERENTIAL)
def test_reassembled_bytes_match_tshark_per_connection_and_direction(name: str) -> None:
    _require_real()
    path = REAL / name
    if not path.exists():
        pytest.skip(f"{name} absent")
    mine: collections.Counter[tuple[int, str]] = collections.Counter()
    for item in read_capture(path):
        if isinstance(item, Chunk):
            mine[(item.stream.id, item.direction.value)] += len(item.data)
    theirs = _tshark_bytes(path)
    assert sum(theirs.values()) > 0
    assert +mine == theirs
