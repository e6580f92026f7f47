"""TCP reassembly rules (mbmon.sources.tcpflow), segment by segment."""

from __future__ import annotations

import dataclasses
import itertools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.sources.tcpflow import ACK, FIN, RST, SYN, TcpConnection, TcpStats, make_chunk

STREAM = Stream(0, Transport.TCP, "10.0.0.1:40000", "10.0.0.2:502")
PSH = 0x08
C_ISN = 1000
S_ISN = 5000


def opened(limit: int = 1 << 20) -> tuple[TcpConnection, list[Chunk | Event]]:
    conn = TcpConnection(STREAM, limit=limit, stats=TcpStats())
    out: list[Chunk | Event] = []
    conn.segment(0.0, True, C_ISN, 0, SYN, b"", out)
    conn.segment(0.1, False, S_ISN, C_ISN + 1, SYN | ACK, b"", out)
    conn.segment(0.2, True, C_ISN + 1, S_ISN + 1, ACK, b"", out)
    return conn, out


def c2s(
    conn: TcpConnection, out: list[Chunk | Event], offset: int, data: bytes, ts: float = 1.0
) -> None:
    """Client data at stream offset ``offset`` (0 = first byte after the SYN)."""
    conn.segment(ts, True, (C_ISN + 1 + offset) & 0xFFFFFFFF, S_ISN + 1, PSH | ACK, data, out)


def delivered(out: list[Chunk | Event], direction: Direction = Direction.C2S) -> bytes:
    return b"".join(i.data for i in out if isinstance(i, Chunk) and i.direction is direction)


def kinds(out: list[Chunk | Event]) -> list[str]:
    return [i.kind.value if isinstance(i, Event) else f"chunk:{i.data.hex()}" for i in out]


def test_handshake_gives_one_connect_even_when_the_syn_is_repeated() -> None:
    conn, out = opened()
    conn.segment(0.3, True, C_ISN, 0, SYN, b"", out)  # SYN retransmission
    assert kinds(out) == ["connect"]
    assert not conn.is_new(True, C_ISN, SYN, False)
    assert conn.is_new(True, C_ISN + 99, SYN, False)


def test_in_order_data_is_delivered_at_once_with_its_timestamp() -> None:
    conn, out = opened()
    c2s(conn, out, 0, b"ab", ts=5.0)
    c2s(conn, out, 2, b"cd", ts=6.0)
    chunks = [i for i in out if isinstance(i, Chunk)]
    assert [(c.ts, c.data, c.direction) for c in chunks] == [
        (5.0, b"ab", Direction.C2S),
        (6.0, b"cd", Direction.C2S),
    ]


def test_retransmission_is_dropped_and_overlap_delivers_only_new_bytes() -> None:
    conn, out = opened()
    c2s(conn, out, 0, b"abcd")
    c2s(conn, out, 0, b"abcd")  # full retransmission
    c2s(conn, out, 2, b"cdef")  # overlap: "ef" is new
    assert kinds(out)[1:] == ["chunk:61626364", "chunk:6566"]
    assert conn.stats.retransmissions == 1
    assert conn.stats.overlaps == 1


def test_out_of_order_segments_wait_for_the_hole() -> None:
    conn, out = opened()
    c2s(conn, out, 4, b"ef", ts=2.0)
    c2s(conn, out, 2, b"cd", ts=3.0)
    assert delivered(out) == b""
    c2s(conn, out, 0, b"ab", ts=4.0)
    assert delivered(out) == b"abcdef"
    # held bytes come out as chunks of their own, each with the time of the packet
    # that carried them, not the time the hole was filled
    assert [(i.ts, i.data) for i in out if isinstance(i, Chunk)] == [
        (4.0, b"ab"),
        (3.0, b"cd"),
        (2.0, b"ef"),
    ]
    assert conn.stats.out_of_order == 2


def test_hole_acknowledged_by_the_peer_becomes_a_gap() -> None:
    conn, out = opened()
    c2s(conn, out, 0, b"ab")
    c2s(conn, out, 5, b"fg")  # bytes 2..4 never captured
    conn.segment(2.0, False, S_ISN + 1, C_ISN + 1 + 7, ACK, b"", out)  # server has all 7
    assert kinds(out)[1:] == ["chunk:6162", "gap", "chunk:6667"]
    gap = out[2]
    assert isinstance(gap, Event)
    assert dict(gap.info) == {"direction": "c2s", "bytes": 3, "reason": "acked-unseen"}
    # an acknowledgement of what was delivered changes nothing
    conn.segment(2.1, False, S_ISN + 1, C_ISN + 1 + 7, ACK, b"", out)
    assert len(out) == 4


def test_requests_released_by_a_reply_come_before_it() -> None:
    conn, out = opened()
    c2s(conn, out, 12, b"req2")  # request 1 (12 bytes) was lost
    conn.segment(2.0, False, S_ISN + 1, C_ISN + 17, PSH | ACK, b"resp", out)
    assert kinds(out)[1:] == ["gap", "chunk:" + b"req2".hex(), "chunk:" + b"resp".hex()]


def test_ack_on_a_fin_or_on_held_data_also_reveals_a_hole() -> None:
    conn, out = opened()
    c2s(conn, out, 2, b"cd")  # client bytes 0..1 never captured
    # the server answers out of order (its byte 0 is missing too), acking all 4
    conn.segment(2.0, False, S_ISN + 2, C_ISN + 5, PSH | ACK, b"y", out)
    assert kinds(out)[1:] == ["gap", "chunk:6364"]
    # its FIN acknowledges as well: the server's own hole stays until the client acks
    conn.segment(2.1, False, S_ISN + 3, C_ISN + 5, FIN | ACK, b"", out)
    conn.segment(2.2, True, C_ISN + 5, S_ISN + 4, FIN | ACK, b"", out)
    assert kinds(out)[3:] == ["gap", "chunk:79", "disconnect"]
    assert [
        e.info["direction"] for e in out if isinstance(e, Event) and e.kind is EventKind.GAP
    ] == [
        "c2s",
        "s2c",
    ]


def test_ack_beyond_everything_seen_skips_to_it_and_continues() -> None:
    conn, out = opened()
    conn.segment(2.0, False, S_ISN + 1, C_ISN + 1 + 10, ACK, b"", out)
    c2s(conn, out, 10, b"k")
    assert kinds(out)[1:] == ["gap", "chunk:6b"]


def test_absurd_ack_is_ignored_as_garbage() -> None:
    conn, out = opened()
    conn.segment(2.0, False, S_ISN + 1, C_ISN + 1 + (1 << 25), ACK, b"", out)
    c2s(conn, out, 0, b"a")
    assert kinds(out)[1:] == ["chunk:61"]


def test_buffer_limit_gives_up_the_hole() -> None:
    conn, out = opened(limit=4)
    c2s(conn, out, 2, b"cd")
    c2s(conn, out, 4, b"ef")
    assert delivered(out) == b""
    c2s(conn, out, 6, b"g")  # 5 held bytes > 4
    assert kinds(out)[1:] == ["gap", "chunk:6364", "chunk:6566", "chunk:67"]
    assert out[1].info["reason"] == "buffer-limit"  # type: ignore[union-attr]


def test_end_of_capture_flushes_holes() -> None:
    conn, out = opened()
    c2s(conn, out, 3, b"d")
    conn.finish(9.0, out)
    assert kinds(out)[1:] == ["gap", "chunk:64"]
    assert out[1].info == {"direction": "c2s", "bytes": 3, "reason": "end-of-capture"}  # type: ignore[union-attr]


def test_sequence_numbers_wrap_around() -> None:
    conn = TcpConnection(STREAM)
    out: list[Chunk | Event] = []
    isn = 0xFFFFFFFD
    conn.segment(0.0, True, isn, 0, SYN, b"", out)
    conn.segment(1.0, True, 0xFFFFFFFE, 0, ACK, b"abc", out)  # crosses 2^32
    conn.segment(2.0, True, 4, 0, ACK, b"gh", out)  # out of order, after the wrap
    conn.segment(3.0, True, 1, 0, ACK, b"def", out)  # fills: 0xFFFFFFFE+3 = 1
    conn.segment(4.0, True, 0xFFFFFFFF, 0, ACK, b"bc", out)  # old bytes
    assert delivered(out) == b"abcdefgh"
    assert conn.stats.retransmissions == 1


def test_mid_stream_start_begins_at_the_first_segment() -> None:
    conn = TcpConnection(STREAM)
    out: list[Chunk | Event] = []
    conn.segment(1.0, False, 777, 0, ACK, b"", out)  # pure ACK: no base yet
    conn.segment(1.1, True, 123456, 777, PSH | ACK, b"xy", out)
    conn.segment(1.2, False, 777, 123458, PSH | ACK, b"z", out)
    assert kinds(out) == ["chunk:7879", "chunk:7a"]  # no CONNECT without a SYN
    assert conn.is_new(True, 5, SYN, False)  # a SYN now is another connection


def test_fin_from_both_sides_gives_one_disconnect_after_all_data() -> None:
    conn, out = opened()
    c2s(conn, out, 0, b"q")
    conn.segment(3.0, True, C_ISN + 2, S_ISN + 1, FIN | ACK, b"", out)  # client half-closes
    # the server still answers, then closes
    conn.segment(3.1, False, S_ISN + 1, C_ISN + 3, PSH | ACK, b"r", out)
    assert "disconnect" not in kinds(out)
    conn.segment(3.2, False, S_ISN + 2, C_ISN + 3, FIN | ACK, b"", out)
    conn.segment(3.3, True, C_ISN + 3, S_ISN + 3, ACK, b"", out)
    assert kinds(out)[1:] == ["chunk:71", "chunk:72", "disconnect"]
    assert out[-1].info == {"how": "fin", "by": "client"}  # type: ignore[union-attr]
    assert conn.closed
    assert conn.is_new(True, C_ISN, SYN, False)  # even the same ISN: the old one ended
    assert conn.is_new(False, S_ISN + 70, SYN | ACK, False)  # its SYN was not captured
    assert not conn.is_new(True, C_ISN + 3, ACK, True)  # a straggler of this connection
    assert conn.is_new(True, C_ISN + 3 + (1 << 21), ACK, True)  # far away: a new one
    assert not conn.is_new(True, C_ISN + 3 + (1 << 21), ACK, False)  # but no payload


def test_fin_that_arrives_before_the_missing_data_waits_for_it() -> None:
    conn, out = opened()
    conn.segment(3.0, False, S_ISN + 1, C_ISN + 1, FIN | ACK, b"", out)
    conn.segment(3.1, True, C_ISN + 3, S_ISN + 2, FIN | ACK, b"cd", out)  # ahead: hole 0..1
    assert "disconnect" not in kinds(out)
    c2s(conn, out, 0, b"ab")
    assert kinds(out)[1:] == ["chunk:6162", "chunk:6364", "disconnect"]
    assert out[-1].info["by"] == "server"  # type: ignore[union-attr]


def test_reset_flushes_and_closes_and_later_payload_is_dropped() -> None:
    conn, out = opened()
    c2s(conn, out, 3, b"d")
    conn.segment(4.0, False, S_ISN + 1, 0, RST, b"", out)
    c2s(conn, out, 4, b"e")
    assert kinds(out)[1:] == ["gap", "chunk:64", "disconnect"]
    assert out[1].info["reason"] == "reset"  # type: ignore[union-attr]
    assert out[-1].info == {"how": "rst", "by": "server"}  # type: ignore[union-attr]
    assert conn.stats.after_close == 1


def test_half_closed_connection_is_closed_by_finish() -> None:
    conn, out = opened()
    conn.segment(3.0, True, C_ISN + 1, S_ISN + 1, FIN | ACK, b"", out)
    conn.finish(9.0, out)
    assert out[-1].kind is EventKind.DISCONNECT  # type: ignore[union-attr]
    assert out[-1].info == {"how": "fin", "by": "client", "half_closed": True}  # type: ignore[union-attr]


def test_open_connection_gets_no_disconnect_at_finish() -> None:
    conn, out = opened()
    conn.finish(9.0, out)
    assert kinds(out) == ["connect"]


@st.composite
def scrambled_stream(draw: st.DrawFn) -> tuple[bytes, list[tuple[int, bytes]], set[int]]:
    """A byte stream cut into segments, some repeated, some re-cut, order shuffled;
    plus a set of segment indexes to drop (lost by the capture)."""
    data = draw(st.binary(min_size=1, max_size=300))
    cuts = (
        sorted(draw(st.sets(st.integers(1, len(data) - 1), max_size=20))) if len(data) > 1 else []
    )
    bounds = [0, *cuts, len(data)]
    segments = [(a, data[a:b]) for a, b in itertools.pairwise(bounds)]
    extra = draw(st.lists(st.sampled_from(segments), max_size=5))  # retransmissions
    overlaps = []
    for _ in range(draw(st.integers(0, 3))):  # segments that straddle others
        a = draw(st.integers(0, len(data) - 1))
        b = draw(st.integers(a + 1, len(data)))
        overlaps.append((a, data[a:b]))
    order = draw(st.permutations(segments + extra + overlaps))
    dropped = draw(st.sets(st.integers(0, len(order) - 1), max_size=3))
    return data, list(order), dropped


@settings(max_examples=250, deadline=None)
@given(scrambled_stream(), st.integers(0, 0xFFFFFFFF))
def test_any_arrival_order_reassembles_the_stream(
    case: tuple[bytes, list[tuple[int, bytes]], set[int]], isn: int
) -> None:
    data, order, _ = case
    conn = TcpConnection(STREAM)
    out: list[Chunk | Event] = []
    conn.segment(0.0, True, isn, 0, SYN, b"", out)
    for offset, seg in order:
        conn.segment(1.0, True, (isn + 1 + offset) & 0xFFFFFFFF, 0, PSH, seg, out)
    assert delivered(out) == data
    assert not [i for i in out if isinstance(i, Event) and i.kind is EventKind.GAP]


@settings(max_examples=250, deadline=None)
@given(scrambled_stream(), st.integers(0, 0xFFFFFFFF))
def test_lost_segments_become_gaps_of_exactly_the_missing_bytes(
    case: tuple[bytes, list[tuple[int, bytes]], set[int]], isn: int
) -> None:
    data, order, dropped = case
    conn = TcpConnection(STREAM)
    out: list[Chunk | Event] = []
    conn.segment(0.0, True, isn, 0, SYN, b"", out)
    conn.segment(0.0, False, 9, (isn + 1) & 0xFFFFFFFF, SYN | ACK, b"", out)
    for i, (offset, seg) in enumerate(order):
        if i not in dropped:
            conn.segment(1.0, True, (isn + 1 + offset) & 0xFFFFFFFF, 10, PSH | ACK, seg, out)
    # the server acknowledges everything, as it received it all
    conn.segment(2.0, False, 10, (isn + 1 + len(data)) & 0xFFFFFFFF, ACK, b"", out)
    # Rebuild the stream: chunks in place, gaps as the original bytes they stand for.
    rebuilt = b""
    for item in out:
        if isinstance(item, Chunk):
            rebuilt += item.data
        elif item.kind is EventKind.GAP:
            assert item.info["bytes"] > 0
            rebuilt += data[len(rebuilt) : len(rebuilt) + item.info["bytes"]]
    assert rebuilt == data


def test_fast_chunk_is_an_ordinary_frozen_chunk() -> None:
    made = make_chunk(1.5, STREAM, Direction.S2C, b"\x01")
    plain = Chunk(1.5, STREAM, Direction.S2C, b"\x01")
    assert type(made) is Chunk
    assert made == plain
    assert hash(made) == hash(plain)
    assert repr(made) == repr(plain)
    with pytest.raises(dataclasses.FrozenInstanceError):
        made.ts = 2.0  # type: ignore[misc]


def test_syn_fin_segment_does_not_close_the_direction() -> None:
    """A fuzzer's SYN+FIN (zeek fuzz-72 frame 1) must not end the sender's direction."""
    conn = TcpConnection(STREAM)
    out: list[Chunk | Event] = []
    conn.segment(1.0, False, 9000, 0, SYN | FIN | PSH, b"abcdef", out)
    conn.segment(1.1, False, 9007, 0, PSH | ACK, b"gh", out)
    assert delivered(out, Direction.S2C) == b"abcdefgh"
    assert "disconnect" not in kinds(out)
