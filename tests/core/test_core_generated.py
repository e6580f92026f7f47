"""The core against the reference pipeline on generated captures: every function code,
link types, cuts at every byte, retransmissions, holes, noise, handshakes and
closes, timeouts and impossible timestamps; random segmentations (hypothesis)."""

from __future__ import annotations

import itertools
import json
import tempfile
from pathlib import Path

import pytest
from core_diff import assert_same, require_core, with_core
from gen import (
    T0,
    adus,
    every_function_pair,
    retransmission_and_overlap,
    split_at_every_byte,
    write_conversation,
    write_frames,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mbmon.io.pcap import TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def test_every_function_code(tmp_path: Path) -> None:
    path = write_conversation(tmp_path / "fc.pcap", adus(every_function_pair()))
    assert_same(path, covered=True)


def test_mid_stream_and_reset(tmp_path: Path) -> None:
    path = tmp_path / "mid.pcap"
    write_conversation(path, adus(every_function_pair()), handshake=False, close="rst")
    assert_same(path, covered=True)


def test_half_closed_and_open_at_the_end(tmp_path: Path) -> None:
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    frames.append(conv.send(True, encode_adu(1, 1, encode_read_request(3, 0, 2))))
    frames.append(conv.segment(True, 0x11))  # FIN-ACK from the client only
    frames.append(conv.send(False, encode_adu(1, 1, encode_read_response(3, [5, 6]))))
    path = write_frames(tmp_path / "half.pcap", [(T0 + i * 0.01, f) for i, f in enumerate(frames)])
    assert_same(path, covered=True)
    open_path = tmp_path / "open.pcap"
    write_conversation(open_path, adus(every_function_pair()[:3]), close=None)
    assert_same(open_path, covered=True)


@pytest.mark.parametrize(
    ("linktype", "pcapng", "vlans"),
    [
        (1, False, ()),
        (1, False, ((0x8100, 5),)),
        (1, True, ((0x88A8, 1), (0x8100, 2))),
        (113, False, ()),
        (276, True, ()),
        (101, False, ()),
        (0, False, ()),
        (108, True, ()),
        (228, False, ()),
    ],
)
def test_link_types(tmp_path: Path, linktype: int, pcapng: bool, vlans: tuple) -> None:
    path = tmp_path / "link.pcapng"
    write_conversation(
        path, adus(every_function_pair()[:6]), linktype=linktype, pcapng=pcapng, vlans=vlans
    )
    assert_same(path, covered=True)


def test_mixed_segments(tmp_path: Path) -> None:
    """Every request in one segment, every answer in one: pairing still in order."""
    pairs = every_function_pair()
    stream = adus(pairs)
    requests = b"".join(a for c, a in stream if c)
    answers = b"".join(a for c, a in stream if not c)
    path = write_conversation(tmp_path / "mixed.pcap", [(True, requests), (False, answers)])
    assert_same(path, covered=True)


def test_splits_at_every_byte(tmp_path: Path) -> None:
    for path in split_at_every_byte(tmp_path):
        assert_same(path, covered=True)


def test_retransmission_and_overlap(tmp_path: Path) -> None:
    assert_same(retransmission_and_overlap(tmp_path), covered=True)


def test_a_hole_at_the_start(tmp_path: Path) -> None:
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    conv.client_next += 12  # 12 bytes never captured
    frames.append(conv.send(True, encode_adu(1, 1, encode_read_request(3, 0, 2))))
    path = write_frames(tmp_path / "hole.pcap", [(T0 + i, f) for i, f in enumerate(frames)])
    assert_same(path, covered=True)
    # more holes, noise, incomplete ADUs at the end: tests/core/test_core_net*.py


def test_timeouts_and_reused_ids(tmp_path: Path) -> None:
    req = encode_adu(1, 1, encode_read_request(3, 0, 2))
    segments = [(True, req), (True, req), (True, encode_adu(2, 1, encode_read_request(4, 0, 1)))]
    segments += [(True, encode_adu(3, 9, encode_read_request(1, 0, 8)))]
    times = [T0, T0 + 0.001, T0 + 0.002] + [T0 + 0.003 + 0.7 * i for i in range(8)]
    path = write_conversation(tmp_path / "to.pcap", segments, times=times)
    assert_same(path, covered=True)
    assert_same(path, covered=True, timeout=0.1)


@pytest.mark.parametrize(
    "times",
    [
        [T0 - i for i in range(20)],  # backwards
        [0.0] * 20,  # the epoch, all at once
        [4294967295.0 - 10 + i * 0.3 for i in range(20)],  # the last second pcap holds
        [T0 + (86400 * 3 if i > 8 else 0) + i for i in range(20)],  # days apart
    ],
    ids=["backwards", "epoch", "end-of-pcap-time", "days"],
)
def test_impossible_timestamps(tmp_path: Path, times: list[float]) -> None:
    path = tmp_path / "time.pcap"
    write_conversation(path, adus(every_function_pair()[:6]), times=times)
    assert_same(path, covered=True)


def _pieces(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in itertools.pairwise(points) if b > a]


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    client_cuts=st.lists(st.integers(0, 10_000), max_size=40),
    server_cuts=st.lists(st.integers(0, 10_000), max_size=40),
    gap=st.sampled_from([0.0005, 0.3, 1.5]),
)
def test_random_segmentations(client_cuts: list[int], server_cuts: list[int], gap: float) -> None:
    """Any cut of the two byte streams gives the same lines through both paths."""
    stream = adus(every_function_pair())
    client = b"".join(a for c, a in stream if c)
    server = b"".join(a for c, a in stream if not c)
    # alternate: each side's pieces interleaved in order (requests keep ahead of answers)
    cs, ss = _pieces(client, client_cuts), _pieces(server, server_cuts)
    segments: list[tuple[bool, bytes]] = []
    while cs or ss:
        if cs:
            segments.append((True, cs.pop(0)))
        if ss:
            segments.append((False, ss.pop(0)))
    with tempfile.TemporaryDirectory() as tmp:
        path = write_conversation(Path(tmp) / "r.pcap", segments, step=gap)
        assert_same(path, covered=True)


def test_no_response_at_the_due_time_and_late_answers(tmp_path: Path) -> None:
    """An unanswered request times out at its time plus the timeout, before the lines
    of the packet that passed that deadline; an answer after it is unsolicited."""
    req = encode_adu(1, 1, encode_read_request(3, 0, 2))
    late = encode_adu(1, 1, encode_read_response(3, [1, 2]))
    nxt = encode_adu(2, 1, encode_read_request(3, 2, 2))
    segments = [(True, req), (False, late), (True, nxt)]
    # handshake (3 frames), the request, its answer 15 s late, a request, the close
    times = [T0, T0, T0, T0 + 0.5, T0 + 15.5, T0 + 16.0] + [T0 + 16.1 + i for i in range(4)]
    path = write_conversation(tmp_path / "late.pcap", segments, times=times)
    assert_same(path, covered=True)
    out, _, why = with_core(path, as_json=True)
    assert why is None
    records = [json.loads(line) for line in out.splitlines()]
    at = next(i for i, r in enumerate(records) if r.get("event") == "timeout")
    assert records[at]["time"] == T0 + 1.5  # the request's time plus 1 s, not the answer's
    assert records[at]["info"]["request_index"] == records[at - 1]["index"]
    late = records[at + 1]  # the answer: no request left to pair it with
    assert (late["kind"], late["request_index"], late["latency_ms"]) == ("response", None, None)


def test_flush_at_the_end_of_a_capture_that_starts_mid_stream(tmp_path: Path) -> None:
    """The realistic case: connections open before the capture, every request answered
    except the last ones; the core reads it (the end's timeouts are mirrored)."""
    stream = adus(every_function_pair()[:8])
    stream += [(True, encode_adu(90, 1, encode_read_request(3, 0, 2)))]
    stream += [(True, encode_adu(91, 1, encode_read_request(4, 0, 2)))]
    times = [T0 + 0.01 * i for i in range(len(stream) - 1)] + [T0 + 5.0]
    path = write_conversation(
        tmp_path / "end.pcap", stream, handshake=False, close=None, times=times
    )
    assert_same(path, covered=True)
    assert_same(path, covered=True, timeout=10.0)  # both decided by the end, not the timeout
    out, _, _ = with_core(path, as_json=True)
    assert out.count(b'"timeout"') == 2


def test_diagnostics_04_is_never_pending(tmp_path: Path) -> None:
    """Force Listen Only Mode (08/0004) gets no answer: never 'No response', an answer
    to it is unsolicited, and it still makes a pending request with its id impossible;
    a truncated 08/0004 counts, an 0x88 request (no sub-function decoded) is held."""
    listen = b"\x08\x00\x04\x00\x00"
    segments = [
        (True, encode_adu(1, 1, listen)),
        (True, encode_adu(2, 1, encode_read_request(3, 0, 2))),
        (True, encode_adu(2, 1, listen)),  # tid 2 reused: the read times out
        (True, encode_adu(3, 1, b"\x08\x00\x04")),  # truncated, still sub-function 04
        (True, encode_adu(4, 1, b"\x08\x00")),  # no sub-function: held
        (True, encode_adu(5, 1, b"\x88\x00\x04\x00\x00")),  # exception bit: held
        (True, encode_adu(6, 1, b"\x08\x00\x01\x00\x00")),  # restart: held, answered
        (False, encode_adu(6, 1, b"\x08\x00\x01\x00\x00")),
        (False, encode_adu(1, 1, listen)),  # an answer to 04: unsolicited
        (True, encode_adu(7, 1, encode_read_request(3, 0, 1))),
        (False, encode_adu(7, 1, encode_read_response(3, [9]))),
    ]
    times = [T0, T0, T0] + [T0 + 0.1 * (i + 1) for i in range(len(segments))]
    times += [T0 + 3.0 + i for i in range(4)]
    path = write_conversation(tmp_path / "listen.pcap", segments, times=times)
    for timeout in (1.0, 0.05):
        assert_same(path, covered=True, timeout=timeout)
    out, _, _ = with_core(path, as_json=True)
    assert out.count(b'"timeout"') == 3  # the reused read, 08 without sub-function, 0x88
