"""The fused reader (mbmon.fastlane) prints exactly what the general flow prints.

Every capture we have, and generated captures full of the cases the fused loop
must hand over (handshakes, retransmissions, out-of-order segments, gaps, noise,
reused transaction ids, timeouts, unsolicited responses, exceptions, bit reads,
RST/FIN, UDP, other ports), is read both ways and compared byte for byte. The
fused loop must also really run: on plain traffic it handles most packets.
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mbmon.fastlane import FastLane
from mbmon.format import View, record_json_bytes
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import (
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_multiple_request,
    encode_write_multiple_response,
    encode_write_single,
)
from mbmon.sources.pcapfile import CaptureConfig, read_capture
from mbmon.sources.pcapwrite import PcapWriter, TcpConversation, udp_frame
from mbmon.sources.tcpflow import ACK, FIN, RST, SYN

REPO = Path(__file__).resolve().parents[1]
REAL = REPO / ".." / "shared" / "captures" / "real"
PSH_ACK = 0x18


def general_output(path: Path, view: View, config: CaptureConfig, timeout: float = 1.0) -> bytes:
    """The JSON lines of the general flow (what ``MBMON_NO_FASTLANE=1`` prints)."""
    pipeline = Pipeline(None, PipelineConfig(timeout=timeout))
    lines: list[bytes] = []
    for item in read_capture(path, config):
        lines += [record_json_bytes(r, view) for r in pipeline.feed(item)]
    lines += [record_json_bytes(r, view) for r in pipeline.finish()]
    return b"".join(line + b"\n" for line in lines)


def lane_output(
    path: Path, view: View, config: CaptureConfig, timeout: float = 1.0
) -> tuple[bytes, FastLane, dict[str, int]]:
    """The JSON lines of the fused reader, the lane itself and the capture statistics."""
    out = io.BytesIO()
    lane = FastLane(Pipeline(None, PipelineConfig(timeout=timeout)), view, out.write)
    stats: dict[str, int] = {}
    for item in read_capture(path, config, stats=stats, lane=lane.bind):
        lane.records(lane.pipeline.feed(item))
    lane.records(lane.pipeline.finish())
    lane.flush(0)
    return out.getvalue(), lane, stats


def same_both_ways(path: Path, view: View | None = None, **config: object) -> FastLane:
    cfg = CaptureConfig(**config)  # type: ignore[arg-type]
    view = view or View()
    expected = general_output(path, view, cfg)
    got, lane, _ = lane_output(path, view, cfg)
    assert got.splitlines() == expected.splitlines()
    assert got == expected
    return lane


def _captures() -> list[object]:
    own = sorted((REPO / "captures").glob("*.pcap"))
    params = [pytest.param(p, id=p.name) for p in own]
    if REAL.is_dir():
        params += [pytest.param(p, id=p.name) for p in sorted(REAL.glob("tcp__*"))]
    else:
        params.append(pytest.param(None, id="real", marks=pytest.mark.skip(
            reason=f"{REAL} absent (real captures are not shipped)")))  # fmt: skip
    return params


@pytest.mark.parametrize("path", _captures())
def test_every_capture_reads_the_same_both_ways(path: Path) -> None:
    same_both_ways(path)
    same_both_ways(path, View(robot="10.0.0.1"))  # robot labels, non-ASCII free


# --------------------------------------------------------------------------- generated


def _bench_like(tmp_path: Path, transactions: int = 3000) -> Path:
    """Plain polling on 4 connections, pipelined and split ADUs: the lane's home ground."""
    path = tmp_path / "plain.pcap"
    convs = [TcpConversation(f"10.0.1.{i + 2}:{40000 + i}", "10.0.0.1:502") for i in range(4)]
    ts = 1_700_000_000.0
    with PcapWriter(path) as w:
        for conv in convs:
            for frm, flags in ((True, SYN), (False, SYN | ACK), (True, ACK)):
                ts += 0.0001
                w.write(ts, conv.segment(frm, flags))
        for n in range(transactions):
            conv = convs[n % 4]
            tid, unit = n & 0xFFFF, 1 + n % 4
            fc = (1, 3, 4, 6, 16)[n % 5]
            if fc in (1, 3, 4):
                req = encode_read_request(fc, n % 50, 1 + n % 9)
                values = [(n * k) & (1 if fc == 1 else 0xFFFF) for k in range(1 + n % 9)]
                resp = encode_read_response(fc, values)
            elif fc == 6:
                req = resp = encode_write_single(6, n % 50, n & 0xFFFF)
            else:
                req = encode_write_multiple_request(16, n % 50, [n & 0xFFFF, 7])
                resp = encode_write_multiple_response(16, n % 50, 2)
            if n % 37 == 0:
                resp = encode_exception(fc, 2)
            a, b = encode_adu(tid, unit, req), encode_adu(tid, unit, resp)
            if n % 11 == 0:  # split over two segments
                for frm, data in ((True, a), (False, b)):
                    for piece in (data[:8], data[8:]):
                        ts += 0.0001
                        w.write(ts, conv.segment(frm, PSH_ACK, piece))
            else:
                ts += 0.0001
                w.write(ts, conv.segment(True, PSH_ACK, a))
                ts += 0.0001
                w.write(ts, conv.segment(False, PSH_ACK, b))
        for conv in convs:
            for frm, flags in ((True, FIN | ACK), (False, FIN | ACK), (True, ACK)):
                ts += 0.0001
                w.write(ts, conv.segment(frm, flags))
    return path


def test_plain_traffic_is_mostly_handled_by_the_fused_loop(tmp_path: Path) -> None:
    path = _bench_like(tmp_path)
    same_both_ways(path)
    _, lane, stats = lane_output(path, View(), CaptureConfig())
    # only the handshakes and FINs (5 packets per connection) go the general way;
    # every ADU, split ones included, is framed, paired and printed by the loop
    assert lane.general_packets == 4 * 5
    assert stats["packets"] > 6000
    assert lane.fast_adus == 2 * 3000


ADUS = [
    encode_adu(1, 1, encode_read_request(3, 10, 2)),
    encode_adu(1, 1, encode_read_response(3, [5, 6])),
    encode_adu(2, 1, encode_read_request(1, 0, 10)),
    encode_adu(2, 1, encode_read_response(1, [1, 0, 1, 1, 0, 0, 1, 0, 1, 1])),
    encode_adu(3, 2, encode_write_single(5, 7, True)),
    encode_adu(3, 2, encode_exception(5, 2)),
    encode_adu(4, 1, encode_read_request(4, 0, 1)),
    encode_adu(4, 1, encode_read_response(4, [9])),
    encode_adu(5, 1, bytes([0x41, 1, 2, 3])),  # a user-defined code
    encode_adu(6, 1, encode_read_request(3, 0, 200)),  # malformed: too many registers
    b"\x00\x07\x00\x01\x00\x06\x01\x03\x00\x00\x00\x01",  # protocol id 1: noise
    b"\xde\xad\xbe\xef",  # garbage
]


@st.composite
def captures(draw: st.DrawFn) -> list[tuple[str, object]]:
    """A script of capture steps on two connections, in time order."""
    steps: list[tuple[str, object]] = []
    for _ in range(draw(st.integers(1, 40))):
        steps.append(draw(st.one_of(
            st.tuples(st.just("data"), st.tuples(
                st.integers(0, 1), st.booleans(), st.lists(st.sampled_from(ADUS), max_size=3),
                st.integers(0, 12))),
            st.tuples(st.just("tcp"), st.tuples(st.integers(0, 1), st.sampled_from(
                ["retransmit", "skip", "swap", "rst", "fin", "syn", "ack-ahead"]))),
            st.tuples(st.just("wait"), st.sampled_from([0.001, 0.5, 2.0])),
            st.tuples(st.just("other"), st.sampled_from(["udp", "port80"])),
        )))  # fmt: skip
    return steps


def _write_script(path: Path, steps: list[tuple[str, object]]) -> None:
    convs = [TcpConversation(f"10.0.0.{i + 5}:{41000 + i}", "10.0.0.1:502") for i in range(2)]
    ts = 1_700_000_000.0
    reopened: dict[int, int] = {}
    with PcapWriter(path) as w:

        def put(frame: bytes) -> None:
            nonlocal ts
            ts += 0.0003
            w.write(ts, frame)

        for conv in convs:
            put(conv.segment(True, SYN))
            put(conv.segment(False, SYN | ACK))
            put(conv.segment(True, ACK))
        for kind, arg in steps:
            if kind == "wait":
                ts += float(arg)  # type: ignore[arg-type]
            elif kind == "other":
                if arg == "udp":
                    put(udp_frame(1, "10.0.0.9", "10.0.0.1", 5000, 502,
                                  encode_adu(9, 1, encode_read_request(3, 0, 1))))  # fmt: skip
                else:
                    put(TcpConversation("10.0.0.9:5555", "10.0.0.1:80").segment(True, PSH_ACK,
                                                                                b"GET /"))
            elif kind == "data":
                i, from_client, adus, cut = arg  # type: ignore[misc]
                data = b"".join(adus)
                if not data:
                    put(convs[i].segment(from_client, ACK))
                    continue
                cut = min(cut, len(data))
                for piece in (data[:cut], data[cut:]) if 0 < cut < len(data) else (data,):
                    put(convs[i].segment(from_client, PSH_ACK, piece))
            else:
                i, what = arg  # type: ignore[misc]
                conv = convs[i]
                payload = encode_adu(7, 1, encode_read_request(3, 1, 1))
                if what == "retransmit":
                    frame = conv.segment(True, PSH_ACK, payload)
                    put(frame)
                    put(frame)
                elif what == "skip":  # a lost segment, then the next one
                    conv.segment(True, PSH_ACK, payload)
                    put(conv.segment(True, PSH_ACK, payload))
                elif what == "swap":  # out of order
                    first = conv.segment(True, PSH_ACK, payload)
                    put(conv.segment(True, PSH_ACK, payload))
                    put(first)
                elif what == "ack-ahead":  # the server acks bytes never seen
                    conv.segment(True, PSH_ACK, payload)
                    put(conv.segment(False, ACK))
                elif what == "rst":
                    put(conv.segment(True, RST | ACK))
                elif what == "fin":
                    put(conv.segment(True, FIN | ACK))
                    put(conv.segment(False, FIN | ACK))
                    put(conv.segment(True, ACK))
                else:  # syn: the same addresses open a new connection
                    reopened[i] = reopened.get(i, 0) + 1
                    convs[i] = TcpConversation(f"10.0.0.{i + 5}:{41000 + i}", "10.0.0.1:502",
                                               client_isn=1000 + 99991 * reopened[i])
                    put(convs[i].segment(True, SYN))
                    put(convs[i].segment(False, SYN | ACK))
                    put(convs[i].segment(True, ACK))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(captures())
def test_generated_captures_read_the_same_both_ways(tmp_path_factory: pytest.TempPathFactory,
                                                    steps: list[tuple[str, object]]) -> None:
    path = tmp_path_factory.mktemp("lane") / "gen.pcap"
    _write_script(path, steps)
    same_both_ways(path)


def test_damaged_capture_same_lines_and_same_message(tmp_path: Path) -> None:
    whole = _bench_like(tmp_path, 200).read_bytes()
    cut = tmp_path / "cut.pcap"
    cut.write_bytes(whole[: len(whole) * 2 // 3])
    runs = {}
    for name, env in (("lane", {}), ("general", {"MBMON_NO_FASTLANE": "1"})):
        runs[name] = subprocess.run(
            [sys.executable, "-m", "mbmon", "read", str(cut), "--json"],
            capture_output=True, env={**os.environ, **env}, check=False,
        )  # fmt: skip
    assert runs["lane"].returncode == runs["general"].returncode == 1
    assert runs["lane"].stdout == runs["general"].stdout
    assert runs["lane"].stdout.count(b"\n") > 100
    assert runs["lane"].stderr == runs["general"].stderr
    assert b"truncated" in runs["lane"].stderr


def test_cli_output_is_the_same_with_the_lane_switched_off(tmp_path: Path) -> None:
    path = _bench_like(tmp_path, 400)
    outs = [
        subprocess.run(
            [sys.executable, "-m", "mbmon", "read", str(path), "--json"],
            capture_output=True, env={**os.environ, **env}, check=True,
        ).stdout
        for env in ({}, {"MBMON_NO_FASTLANE": "1"})
    ]  # fmt: skip
    assert outs[0] == outs[1] and outs[0].count(b"\n") > 800
