"""Pairing: MBAP by transaction id, RTU by bus order, timeouts, unsolicited, broadcast."""

from __future__ import annotations

from dataclasses import replace

import pytest

from mbmon.model import Direction, Frame, Kind, Stream, Transaction, Transport, TxStatus
from mbmon.protocol.mbap import MbapDecoder, encode_adu
from mbmon.protocol.pairing import Pairer
from mbmon.protocol.pdu import (
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_single,
)
from mbmon.protocol.rtu import RtuDecoder, encode_rtu

TCP = Stream(0, Transport.TCP, "10.0.0.2:50000", "10.0.0.1:502")
TCP2 = Stream(1, Transport.TCP, "10.0.0.3:50001", "10.0.0.1:502")
BUS = Stream(2, Transport.RTU, "/dev/ttyS0", "/dev/ttyS0")


def tcp(stream: Stream, direction: Direction, tid: int, unit: int, pdu: bytes, ts: float) -> Frame:
    """One MBAP frame, made by the real decoder."""
    [f] = MbapDecoder(stream, direction).feed(encode_adu(tid, unit, pdu), ts)
    assert isinstance(f, Frame)
    return f


def req(tid: int, ts: float, unit: int = 1, stream: Stream = TCP, addr: int = 0) -> Frame:
    return tcp(stream, Direction.C2S, tid, unit, encode_read_request(3, addr, 2), ts)


def resp(tid: int, ts: float, unit: int = 1, stream: Stream = TCP) -> Frame:
    return tcp(stream, Direction.S2C, tid, unit, encode_read_response(3, [tid, 7]), ts)


def rtu(adu_pdus: list[tuple[int, bytes]], ts: float) -> list[Frame]:
    """RTU frames from one bus byte stream, made by the real decoder."""
    dec = RtuDecoder(BUS)
    data = b"".join(encode_rtu(unit, pdu) for unit, pdu in adu_pdus)
    out = dec.feed(data, ts) + dec.flush(ts)
    assert all(isinstance(x, Frame) for x in out)
    return [x for x in out if isinstance(x, Frame)]


def statuses(txs: list[Transaction]) -> list[TxStatus]:
    return [t.status for t in txs]


def test_request_is_pending_then_answered() -> None:
    p = Pairer()
    q = req(1, 10.0)
    [t] = p.feed(q)
    assert (t.status, t.request, t.response, t.ts, t.latency) == (
        TxStatus.PENDING,
        q,
        None,
        10.0,
        None,
    )
    assert t.frame is q
    r = resp(1, 10.25)
    [a] = p.feed(r)
    assert a.status is TxStatus.ANSWERED
    assert a.request is q
    assert a.response is not None and a.response.raw == r.raw
    assert a.latency == pytest.approx(0.25)
    assert a.ts == 10.25
    assert a.frame is a.response
    assert p.pending_count == 0


def test_tcp_out_of_order_responses_pair_by_tid() -> None:
    p = Pairer()
    reqs = {tid: req(tid, float(tid), addr=100 * tid) for tid in (1, 2, 3)}
    for q in reqs.values():
        assert statuses(p.feed(q)) == [TxStatus.PENDING]
    for tid, ts in ((3, 5.0), (1, 6.0), (2, 7.0)):
        [a] = p.feed(resp(tid, ts))
        assert a.status is TxStatus.ANSWERED
        assert a.request is reqs[tid]
        assert a.request.pdu.address == 100 * tid
        assert a.latency == pytest.approx(ts - tid)
    assert p.flush(99.0) == []


def test_tcp_unit_must_agree() -> None:
    p = Pairer()
    p.feed(req(1, 1.0, unit=1))
    [a] = p.feed(resp(1, 1.1, unit=2))
    assert a.status is TxStatus.UNSOLICITED
    assert (a.request, a.latency) == (None, None)
    [b] = p.feed(resp(1, 1.2, unit=1))
    assert b.status is TxStatus.ANSWERED


def test_streams_are_kept_apart() -> None:
    p = Pairer()
    q1, q2 = req(1, 1.0, stream=TCP), req(1, 2.0, stream=TCP2)
    p.feed(q1)
    p.feed(q2)
    [a] = p.feed(resp(1, 3.0, stream=TCP2))
    assert a.request is q2
    [b] = p.feed(resp(1, 4.0, stream=TCP))
    assert b.request is q1


def test_exception_response_latency() -> None:
    p = Pairer()
    q = req(7, 2.0)
    p.feed(q)
    e = tcp(TCP, Direction.S2C, 7, 1, encode_exception(3, 2), 2.004)
    [a] = p.feed(e)
    assert a.status is TxStatus.EXCEPTION
    assert a.response is not None and a.response.pdu.exception_code == 2
    assert a.latency == pytest.approx(0.004)


def test_unsolicited_response() -> None:
    p = Pairer()
    r = resp(9, 1.0)
    [a] = p.feed(r)
    assert (a.status, a.request, a.response, a.ts) == (TxStatus.UNSOLICITED, None, r, 1.0)
    assert a.frame is r


def test_timeout_via_tick_then_late_response_is_unsolicited() -> None:
    p = Pairer(timeout=1.0)
    q1, q2 = req(1, 10.0), req(2, 10.6)
    p.feed(q1)
    p.feed(q2)
    assert p.tick(10.9) == []
    [t] = p.tick(11.2)
    # stamped when the answer was due (10.0 + 1.0), not when the tick came
    assert (t.status, t.request, t.response, t.ts) == (TxStatus.TIMEOUT, q1, None, 11.0)
    assert t.frame is None
    [t2] = p.tick(12.0)
    assert (t2.request, t2.ts) == (q2, 11.6)
    assert p.tick(50.0) == []
    [late] = p.feed(resp(1, 12.5))
    assert late.status is TxStatus.UNSOLICITED


def test_flush_times_out_everything_pending() -> None:
    p = Pairer(timeout=100.0)
    qs = [req(1, 1.0), req(2, 2.0), req(1, 3.0, stream=TCP2)]
    for q in qs:
        p.feed(q)
    out = p.flush(5.0)  # before any answer was due: at the end of the input
    assert statuses(out) == [TxStatus.TIMEOUT] * 3
    assert {id(t.request) for t in out} == {id(q) for q in qs}
    assert all(t.ts == 5.0 for t in out)
    assert p.flush(6.0) == []
    assert p.pending_count == 0


def test_tid_reuse_replaces_old_request() -> None:
    p = Pairer()
    old, new = req(5, 1.0, addr=1), req(5, 2.0, addr=2)
    p.feed(old)
    out = p.feed(new)
    assert statuses(out) == [TxStatus.TIMEOUT, TxStatus.PENDING]
    assert (out[0].request, out[0].ts) == (old, 2.0)
    assert out[1].request is new
    [a] = p.feed(resp(5, 2.5))
    assert a.request is new
    assert a.latency == pytest.approx(0.5)


def test_pending_is_capped_per_stream() -> None:
    p = Pairer(max_pending=3)
    qs = [req(tid, float(tid)) for tid in range(5)]
    out: list[Transaction] = []
    for q in qs:
        out += p.feed(q)
    timeouts = [t for t in out if t.status is TxStatus.TIMEOUT]
    assert [t.request for t in timeouts] == qs[:2]
    assert p.pending_count == 3


def test_response_is_redecoded_with_its_request() -> None:
    # 19 coils requested; the 3-byte response carries 24 bits: trimmed to 19.
    p = Pairer()
    q = tcp(TCP, Direction.C2S, 1, 1, encode_read_request(1, 0x13, 19), 1.0)
    bits = [1, 0, 1, 1, 0, 0, 1, 1] * 3
    r = tcp(TCP, Direction.S2C, 1, 1, encode_read_response(1, bits), 1.1)
    assert r.pdu.values is not None and len(r.pdu.values) == 24
    p.feed(q)
    [a] = p.feed(r)
    assert a.response is not None
    assert a.response.pdu.values == tuple(bits[:19])
    assert a.response.raw == r.raw
    assert (a.response.ts, a.response.tid, a.response.stream) == (r.ts, r.tid, r.stream)


# ---------------------------------------------------------------- RTU


def test_rtu_pairs_by_order() -> None:
    frames = rtu(
        [
            (1, encode_read_request(3, 0, 2)),
            (1, encode_read_response(3, [1, 2])),
            (2, encode_read_request(4, 0, 1)),
            (2, encode_read_response(4, [9])),
        ],
        5.0,
    )
    assert [f.direction for f in frames] == [Direction.C2S, Direction.S2C] * 2
    frames = [replace(f, ts=5.0 + i * 0.1) for i, f in enumerate(frames)]
    p = Pairer()
    out: list[Transaction] = []
    for f in frames:
        out += p.feed(f)
    assert statuses(out) == [TxStatus.PENDING, TxStatus.ANSWERED] * 2
    assert out[1].request is frames[0]
    assert out[3].request is frames[2]
    assert out[3].latency == pytest.approx(0.1)


def test_rtu_response_from_other_unit_or_function_is_unsolicited() -> None:
    q, r = rtu([(1, encode_read_request(3, 0, 1)), (1, encode_read_response(3, [5]))], 1.0)
    # Frames as they would come from a bus where someone else answered:
    other_unit = rtu([(2, encode_read_request(3, 0, 1)), (2, encode_read_response(3, [5]))], 1.0)
    other_fc = rtu([(1, encode_read_request(4, 0, 1)), (1, encode_read_response(4, [5]))], 1.0)
    p = Pairer()
    p.feed(q)
    [a] = p.feed(other_unit[1])
    assert a.status is TxStatus.UNSOLICITED
    [b] = p.feed(other_fc[1])
    assert b.status is TxStatus.UNSOLICITED
    [c] = p.feed(r)
    assert (c.status, c.request) == (TxStatus.ANSWERED, q)


def test_rtu_new_request_times_out_the_pending_one() -> None:
    q1, q2 = rtu([(1, encode_read_request(3, 0, 1)), (2, encode_read_request(3, 0, 1))], 1.0)
    p = Pairer()
    p.feed(q1)
    out = p.feed(q2)
    assert statuses(out) == [TxStatus.TIMEOUT, TxStatus.PENDING]
    assert out[0].request is q1
    assert out[1].request is q2


def test_rtu_exception() -> None:
    q, e = rtu([(1, encode_read_request(4, 2999, 1)), (1, encode_exception(4, 2))], 1.0)
    assert e.pdu.kind is Kind.EXCEPTION
    p = Pairer()
    p.feed(q)
    [a] = p.feed(e)
    assert (a.status, a.request) == (TxStatus.EXCEPTION, q)
    assert a.latency == 0.0


def test_rtu_broadcast_never_pends() -> None:
    [b] = rtu([(0, encode_write_single(6, 1, 3))], 1.0)
    assert b.unit == 0
    p = Pairer(timeout=0.5)
    [t] = p.feed(b)
    assert (t.status, t.request) == (TxStatus.PENDING, b)
    assert p.pending_count == 0
    assert p.tick(10.0) == []
    assert p.flush(11.0) == []


def test_rtu_broadcast_after_unanswered_request() -> None:
    [q] = rtu([(1, encode_read_request(3, 0, 1))], 1.0)
    [b] = rtu([(0, encode_write_single(6, 1, 3))], 2.0)
    p = Pairer()
    p.feed(q)
    out = p.feed(b)
    assert statuses(out) == [TxStatus.TIMEOUT, TxStatus.PENDING]
    assert p.pending_count == 0


def test_tcp_unit_zero_is_not_a_broadcast() -> None:
    p = Pairer()
    p.feed(req(1, 1.0, unit=0))
    [a] = p.feed(resp(1, 1.5, unit=0))
    assert a.status is TxStatus.ANSWERED


def test_every_frame_yields_exactly_one_step() -> None:
    p = Pairer(timeout=1.0, max_pending=2)
    frames = [req(1, 0.0), req(2, 0.1), req(1, 0.2), resp(2, 0.3), resp(8, 0.4), req(3, 0.5)]
    frames += [req(4, 0.6), resp(4, 0.7)]
    steps: list[Transaction] = []
    for f in frames:
        out = p.feed(f)
        non_timeouts = [t for t in out if t.status is not TxStatus.TIMEOUT]
        assert len(non_timeouts) == 1
        assert non_timeouts[0].frame is not None
        assert non_timeouts[0].frame.raw == f.raw
        steps += out
    steps += p.flush(9.0)
    # every request ends exactly once: answered or timed out
    ended = [t.request for t in steps if t.status in (TxStatus.ANSWERED, TxStatus.TIMEOUT)]
    started = [f for f in frames if f.direction is Direction.C2S]
    assert sorted(id(x) for x in ended) == sorted(id(x) for x in started)


def test_timeouts_are_stamped_when_due_not_when_a_later_packet_comes() -> None:
    p = Pairer(timeout=1.0)
    q = req(1, 10.0)
    p.feed(q)
    [t] = p.tick(25.0)  # the next packet came 15 s later
    assert (t.request, t.ts) == (q, 11.0)
    # end of input long after: at the due time too
    p.feed(req(2, 30.0))
    [f] = p.flush(99.0)
    assert f.ts == 31.0
    # a tid reused after the timeout: the old one was due at its own time
    p.feed(req(3, 40.0))
    out = p.feed(req(3, 45.0))
    assert (out[0].status, out[0].ts) == (TxStatus.TIMEOUT, 41.0)


def test_diagnostics_force_listen_only_is_never_pending() -> None:
    from mbmon.protocol.pairing import expects_reply

    listen_only = tcp(TCP, Direction.C2S, 7, 1, bytes.fromhex("08 0004 0000"), 1.0)
    restart = tcp(TCP, Direction.C2S, 8, 1, bytes.fromhex("08 0001 0000"), 1.0)
    [bus_listen_only] = rtu([(1, bytes.fromhex("08 0004 0000"))], 1.0)
    assert not expects_reply(bus_listen_only)
    assert not expects_reply(listen_only) and expects_reply(restart)
    p = Pairer(timeout=1.0)
    assert statuses(p.feed(listen_only)) == [TxStatus.PENDING]
    assert p.pending_count == 0
    assert p.tick(5.0) == [] and p.flush(9.0) == []
    p.feed(restart)
    assert p.pending_count == 1
