"""The core against the reference pipeline on what the network layers bring: MBAP noise
and its resynchronisation, MBAP length 255, an incomplete ADU at a disconnect or at
the end (noise), byte for byte, text and JSON (and the MCAP log); random cuts of noisy
streams (hypothesis)."""

from __future__ import annotations

import itertools
import json
import tempfile
from pathlib import Path

import pytest
from core_diff import REAL, assert_same, require_core, with_core
from gen import T0, adus, every_function_pair, noisy_stream, write_conversation
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap_diff import assert_same_log

from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def _req(tid: int, address: int = 0) -> bytes:
    return encode_adu(tid, 1, encode_read_request(3, address, 2))


def _resp(tid: int) -> bytes:
    return encode_adu(tid, 1, encode_read_response(3, [tid, 7]))


def test_noise_then_resynchronisation(tmp_path: Path) -> None:
    """Garbage between ADUs, in both directions: one noise record per run, the frames
    after it found again (a resync candidate corroborated), and paired."""
    segments = [
        (True, _req(1)),
        (False, _resp(1)),
        (True, b"\x01\x02\x03garbage!" * 3 + _req(2)),
        (False, b"\xff\xfe" + _resp(2)),
        (True, _req(3) + b"\x00\x00\x00\x00\x00\x00\x00" + _req(4)),
        (False, _resp(3) + _resp(4)),
        (True, _req(5)),
        (False, _resp(5)),
    ]
    path = write_conversation(tmp_path / "noise.pcap", segments)
    assert_same(path, covered=True)
    out, summary, _ = with_core(path, as_json=True)
    records = [json.loads(line) for line in out.splitlines()]
    assert sum(r["kind"] == "noise" for r in records) >= 3
    assert "noise" in summary
    assert sum(r["kind"] == "response" and r["request_index"] is not None for r in records) == 5


def test_a_capture_that_starts_inside_an_adu(tmp_path: Path) -> None:
    """The first segment of each direction starts mid-ADU (a capture begun mid-stream):
    noise, then the core frames the direction again."""
    stream = adus(every_function_pair())
    client = b"".join(a for c, a in stream if c)
    server = b"".join(a for c, a in stream if not c)
    segments = [(True, client[5:40]), (False, server[3:30]), (True, client[40:])]
    segments.append((False, server[30:]))
    path = write_conversation(tmp_path / "mid.pcap", segments, handshake=False, close=None)
    assert_same(path, covered=True)


def test_mbap_length_255(tmp_path: Path) -> None:
    """Length 255 (one over the spec) is a frame marked malformed, paired like any other;
    alone, after noise, and as the answer of a read."""
    long_req = bytes((0, 9, 0, 0, 0, 255, 1, 0x5A)) + bytes(range(253))
    long_resp = bytes((0, 9, 0, 0, 0, 255, 1, 0x5A)) + bytes(253)
    read_req = _req(10)
    read_resp = bytes((0, 10, 0, 0, 0, 255, 1, 3, 252)) + bytes(252)
    segments = [
        (True, long_req),
        (False, long_resp),
        (True, read_req),
        (False, read_resp),
        (True, b"junk" + long_req[:100]),
        (True, long_req[100:] + _req(11)),
        (False, _resp(11)),
    ]
    path = write_conversation(tmp_path / "l255.pcap", segments)
    assert_same(path, covered=True)
    out, summary, _ = with_core(path, as_json=True)
    records = [json.loads(line) for line in out.splitlines()]
    assert any("MBAP length 255" in (r.get("malformed") or "") for r in records)
    assert "malformed" in summary


@pytest.mark.parametrize("close", ["fin", "rst", None])
def test_an_incomplete_adu_at_the_end(tmp_path: Path, close: str | None) -> None:
    """Bytes held when the connection ends (FIN both ways, a reset) or at the end of the
    capture: noise at the time they arrived, before the requests' timeouts."""
    segments = [
        (True, _req(1)),
        (False, _resp(1)),
        (True, _req(2)),
        (True, _req(3)[:9]),
        (False, _resp(2)[:4]),
    ]
    path = write_conversation(tmp_path / "tail.pcap", segments, close=close)
    assert_same(path, covered=True)
    out, _, _ = with_core(path, as_json=True)
    kinds = [json.loads(line)["kind"] for line in out.splitlines()]
    assert kinds.count("noise") == 2


def test_a_resync_candidate_judged_at_the_end(tmp_path: Path) -> None:
    """After noise, a header of a code with no predictable length waits for what follows;
    at the end of the stream it is judged with the bytes present (a frame)."""
    user = encode_adu(4, 1, b"\x41\x01\x02\x03")
    segments = [(True, _req(1)), (True, b"\x05\x06\x07\x08\x09" + user)]
    for close in ("fin", None):
        path = write_conversation(tmp_path / f"cand{close}.pcap", segments, close=close)
        assert_same(path, covered=True)


def test_held_bytes_before_noise_keep_their_time(tmp_path: Path) -> None:
    """Fewer than 6 bytes held, then bytes that make them no header: the noise run is
    stamped when the held bytes arrived."""
    segments = [(True, _req(1)), (True, b"\x00\x01\x00"), (True, b"\x07\x00\x06" + _req(2))]
    times = [T0, T0, T0, T0 + 0.5, T0 + 1.0, T0 + 1.7] + [T0 + 2 + i for i in range(4)]
    path = write_conversation(tmp_path / "held.pcap", segments, times=times)
    assert_same(path, covered=True)
    out, _, _ = with_core(path, as_json=True)
    noise = [r for r in map(json.loads, out.splitlines()) if r["kind"] == "noise"]
    assert noise and noise[0]["time"] == T0 + 1.0


def test_noise_with_a_log(tmp_path: Path) -> None:
    segments = noisy_stream(seed=3)
    path = write_conversation(tmp_path / "log.pcap", segments)
    assert_same_log(path, tmp_path, covered=True)


def test_real_captures_with_noise() -> None:
    names = ["tcp__arkime__modbus_merged.pcap", "tcp__digitalbond__modbus_test_data_part1.pcap"]
    paths = [REAL / name for name in names if (REAL / name).is_file()]
    if not paths:
        pytest.skip(f"{REAL} absent (../shared/captures/real)")
    for path in paths:
        assert_same(path, covered=True)


def _pieces(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in itertools.pairwise(points) if b > a]


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    seed=st.integers(0, 2**16),
    client_cuts=st.lists(st.integers(0, 10_000), max_size=25),
    server_cuts=st.lists(st.integers(0, 10_000), max_size=25),
    close=st.sampled_from(["fin", "rst", None]),
)
def test_random_cuts_of_noisy_streams(
    seed: int, client_cuts: list[int], server_cuts: list[int], close: str | None
) -> None:
    """Any cut of two noisy byte streams gives the same lines through both paths."""
    stream = noisy_stream(seed)
    client = b"".join(a for c, a in stream if c)
    server = b"".join(a for c, a in stream if not c)
    cs, ss = _pieces(client, client_cuts), _pieces(server, server_cuts)
    segments: list[tuple[bool, bytes]] = []
    while cs or ss:
        if cs:
            segments.append((True, cs.pop(0)))
        if ss:
            segments.append((False, ss.pop(0)))
    with tempfile.TemporaryDirectory() as tmp:
        path = write_conversation(Path(tmp) / "r.pcap", segments, close=close)
        assert_same(path, covered=True)
