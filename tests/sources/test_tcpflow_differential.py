"""``TcpConnection.segment``'s fast branch against its general path: the same
random conversation (any segmentation, reordered, repeated, with or without the
handshake, FINs, RSTs, wraparound) gives the same chunks, events, counters and
watcher calls when every segment goes the general way."""

from __future__ import annotations

from itertools import pairwise
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.model import Chunk, Event, Stream, Transport
from mbmon.sources.tcpflow import ACK, FIN, RST, SYN, TcpConnection, TcpStats

STREAM = Stream(0, Transport.TCP, "10.0.0.1:40000", "10.0.0.2:502")
PSH = 0x08
MASK = 0xFFFFFFFF

Segment = tuple[float, bool, int, int, int, bytes]


class Watch:
    """Records what the connection tells its watcher."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, float]] = []

    def held(self, conn: TcpConnection, ts: float) -> None:
        self.calls.append(("held", ts))

    def closed(self, conn: TcpConnection, ts: float) -> None:
        self.calls.append(("closed", ts))


def _cuts(draw: Any, data: bytes) -> list[tuple[int, bytes]]:
    """``data`` cut at random points: ``(offset, piece)`` in order."""
    points = sorted(set(draw(st.lists(st.integers(1, max(1, len(data))), max_size=8))))
    bounds = [0, *[p for p in points if p < len(data)], len(data)]
    return [(a, data[a:b]) for a, b in pairwise(bounds) if b > a]


@st.composite
def conversations(draw: Any) -> tuple[list[Segment], int]:
    c_isn = draw(st.one_of(st.integers(0, MASK), st.integers(MASK - 300, MASK)))
    s_isn = draw(st.one_of(st.integers(0, MASK), st.integers(MASK - 300, MASK)))
    c_data = draw(st.binary(max_size=120))
    s_data = draw(st.binary(max_size=120))
    segs: list[Segment] = []
    if draw(st.booleans()):  # the handshake was captured
        segs.append((0.0, True, c_isn, 0, SYN, b""))
        segs.append((0.0, False, s_isn, (c_isn + 1) & MASK, SYN | ACK, b""))
        segs.append((0.0, True, (c_isn + 1) & MASK, (s_isn + 1) & MASK, ACK, b""))
    c_pieces = [(True, off, piece) for off, piece in _cuts(draw, c_data)]
    s_pieces = [(False, off, piece) for off, piece in _cuts(draw, s_data)]
    pieces = c_pieces + s_pieces
    order = draw(st.permutations(range(len(pieces)))) if draw(st.booleans()) else None
    if order is None:  # interleaved in order per direction
        pieces = sorted(pieces, key=lambda p: (p[1], not p[0]))
    else:
        pieces = [pieces[i] for i in order]
    acked = {True: 0, False: 0}  # what each side has sent so far (in offsets)
    for from_client, off, piece in pieces:
        isn, other_isn = (c_isn, s_isn) if from_client else (s_isn, c_isn)
        seq = (isn + 1 + off) & MASK
        ack_at = draw(st.sampled_from(["seen", "none", "ahead"]))
        if ack_at == "none":
            flags, ack = PSH, 0
        else:
            extra = draw(st.integers(1, 40)) if ack_at == "ahead" else 0
            flags, ack = PSH | ACK, (other_isn + 1 + acked[not from_client] + extra) & MASK
        segs.append((0.0, from_client, seq, ack, flags, piece))
        acked[from_client] = max(acked[from_client], off + len(piece))
        if draw(st.integers(0, 5)) == 0:  # a retransmission, maybe cut differently
            segs.append((0.0, from_client, seq, ack, flags, piece[: draw(st.integers(1, 8))]))
    end = draw(st.sampled_from(["none", "fin", "fins", "rst", "syn-again"]))
    c_end, s_end = (c_isn + 1 + len(c_data)) & MASK, (s_isn + 1 + len(s_data)) & MASK
    if end in ("fin", "fins"):
        segs.append((0.0, True, c_end, s_end, FIN | ACK, b""))
    if end == "fins":
        segs.append((0.0, False, s_end, (c_end + 1) & MASK, FIN | ACK, b""))
    if end == "rst":
        segs.append((0.0, draw(st.booleans()), c_end, s_end, RST | ACK, b""))
    if end == "syn-again":
        segs.append((0.0, True, draw(st.integers(0, MASK)), 0, SYN, b""))
    if draw(st.booleans()):  # payload after the end
        segs.append((0.0, True, c_end, s_end, PSH | ACK, b"late"))
    timed = [(i * 0.01, *seg[1:]) for i, seg in enumerate(segs)]
    limit = draw(st.sampled_from([1 << 20, 16, 40]))
    return timed, limit


def _run(segments: list[Segment], limit: int, general: bool) -> tuple[Any, ...]:
    watch = Watch()
    stats = TcpStats()
    conn = TcpConnection(STREAM, limit=limit, stats=stats, watcher=watch)
    take = conn.segment_general if general else conn.segment
    out: list[Chunk | Event] = []
    for ts, from_client, seq, ack, flags, payload in segments:
        take(ts, from_client, seq, ack, flags, payload, out)
    conn.finish(99.0, out)
    return out, stats.as_dict(), watch.calls, conn.connected, conn.closed, conn.fin_by, conn.last


@settings(max_examples=300, deadline=None)
@given(conversations())
def test_the_fast_branch_gives_what_the_general_path_gives(conv: tuple[list[Segment], int]) -> None:
    segments, limit = conv
    assert _run(segments, limit, general=False) == _run(segments, limit, general=True)


def test_the_general_path_is_taken_for_every_segment() -> None:
    """The reference really is the general path: an in-order segment, which the fast
    branch delivers, comes out the same through ``segment_general`` alone."""
    conn = TcpConnection(STREAM, stats=TcpStats())
    out: list[Chunk | Event] = []
    conn.segment_general(0.0, True, 10, 0, SYN, b"", out)
    conn.segment_general(0.1, True, 11, 0, PSH, b"ab", out)
    conn.segment_general(0.2, True, 13, 0, PSH, b"cd", out)
    assert [i.data for i in out if isinstance(i, Chunk)] == [b"ab", b"cd"]
