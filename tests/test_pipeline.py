"""The wiring: chunks and events in, records out, for every transport."""

from __future__ import annotations

from mbmon.model import Chunk, Direction, Event, EventKind, RecordKind, Stream, Transport
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import (
    encode_exception,
    encode_read_request,
    encode_read_response,
    encode_write_single,
)
from mbmon.protocol.rtu import encode_rtu
from mbmon.semantics.annotate import Annotator
from mbmon.semantics.profile import ProfileBinding

TCP = Stream(0, Transport.TCP, "10.0.0.1:50000", "10.0.0.2:502")
UDP = Stream(1, Transport.UDP, "10.0.0.1:50001", "10.0.0.2:502")
BUS = Stream(2, Transport.RTU, "bus.bin", "bus.bin")
RTU_TCP = Stream(3, Transport.RTU_OVER_TCP, "10.0.0.1:50002", "10.0.0.2:4001")


def c2s(stream: Stream, ts: float, data: bytes) -> Chunk:
    return Chunk(ts, stream, Direction.C2S, data)


def s2c(stream: Stream, ts: float, data: bytes) -> Chunk:
    return Chunk(ts, stream, Direction.S2C, data)


def run(items, annotator=None, timeout: float = 1.0):
    pipe = Pipeline(annotator, PipelineConfig(timeout=timeout))
    return list(pipe.run(items))


def test_tcp_request_response_indexes_and_latency() -> None:
    recs = run(
        [
            c2s(TCP, 1.0, encode_adu(5, 1, encode_read_request(3, 400, 2))),
            s2c(TCP, 1.004, encode_adu(5, 1, encode_read_response(3, [1, 2]))),
        ]
    )
    assert [r.kind for r in recs] == [RecordKind.REQUEST, RecordKind.RESPONSE]
    assert [r.index for r in recs] == [0, 1]
    assert recs[1].request_index == 0 and recs[1].request is recs[0].frame
    assert abs(recs[1].latency - 0.004) < 1e-9


def test_unanswered_request_becomes_timeout_event_naming_the_request() -> None:
    recs = run(
        [
            c2s(TCP, 1.0, encode_adu(1, 1, encode_read_request(3, 0, 1))),
            c2s(TCP, 3.0, encode_adu(2, 1, encode_read_request(3, 0, 1))),
            s2c(TCP, 3.001, encode_adu(2, 1, encode_read_response(3, [7]))),
        ]
    )
    timeouts = [r for r in recs if r.kind is RecordKind.EVENT]
    assert len(timeouts) == 1 and timeouts[0].event.kind is EventKind.TIMEOUT
    assert timeouts[0].event.info["request_index"] == 0
    response = next(r for r in recs if r.kind is RecordKind.RESPONSE)
    assert response.request.tid == 2


def test_exception_record_kind() -> None:
    recs = run(
        [
            c2s(TCP, 1.0, encode_adu(9, 1, encode_read_request(3, 9999, 1))),
            s2c(TCP, 1.001, encode_adu(9, 1, encode_exception(3, 2))),
        ]
    )
    assert recs[1].kind is RecordKind.EXCEPTION and recs[1].request_index == 0


def test_gap_resets_the_decoder_and_later_adus_still_decode() -> None:
    adu = encode_adu(1, 1, encode_read_request(3, 0, 1))
    recs = run(
        [
            c2s(TCP, 1.0, adu[:4]),
            Event(1.1, TCP, EventKind.GAP, {"direction": "c2s", "bytes": 20}),
            c2s(TCP, 1.2, encode_adu(2, 1, encode_read_request(3, 10, 1))),
        ]
    )
    kinds = [r.kind for r in recs]
    assert kinds[:2] == [RecordKind.NOISE, RecordKind.EVENT]
    assert recs[0].noise.raw == adu[:4]
    requests = [r for r in recs if r.kind is RecordKind.REQUEST]
    assert len(requests) == 1 and requests[0].frame.pdu.address == 10


def test_udp_datagrams_do_not_run_into_each_other() -> None:
    good = encode_adu(1, 1, encode_read_request(4, 0, 2))
    recs = run([c2s(UDP, 1.0, good[:-1]), c2s(UDP, 1.1, good)])
    assert [r.kind for r in recs][:2] == [RecordKind.NOISE, RecordKind.REQUEST]


def test_rtu_bus_both_directions_in_one_stream() -> None:
    req = encode_rtu(1, encode_read_request(3, 0, 2))
    resp = encode_rtu(1, encode_read_response(3, [10, 20]))
    recs = run(
        [Chunk(1.0, BUS, Direction.BUS, req + resp[:3]), Chunk(1.01, BUS, Direction.BUS, resp[3:])]
    )
    assert [r.kind for r in recs] == [RecordKind.REQUEST, RecordKind.RESPONSE]
    assert recs[1].frame.direction is Direction.S2C and recs[1].frame.crc_ok is True
    assert recs[1].frame.pdu.values == (10, 20)


def test_rtu_over_tcp_uses_the_tcp_direction() -> None:
    req = encode_rtu(7, encode_write_single(6, 200, 1))
    recs = run([c2s(RTU_TCP, 1.0, req), s2c(RTU_TCP, 1.002, req)])
    assert [r.kind for r in recs] == [RecordKind.REQUEST, RecordKind.RESPONSE]
    assert recs[1].request_index == 0


def test_disconnect_flushes_the_stream() -> None:
    adu = encode_adu(1, 1, encode_read_request(3, 0, 1))
    recs = run([c2s(TCP, 1.0, adu[:5]), Event(2.0, TCP, EventKind.DISCONNECT, {"how": "rst"})])
    assert [r.kind for r in recs] == [RecordKind.EVENT, RecordKind.NOISE]
    assert recs[1].noise.reason.startswith("truncated")


def test_commands_follow_their_frame() -> None:
    annotator = Annotator(ProfileBinding.parse(["hrss"]))
    recs = run(
        [
            c2s(TCP, 1.0, encode_adu(1, 1, encode_write_single(6, 200, 1))),
            s2c(TCP, 1.001, encode_adu(1, 1, encode_write_single(6, 200, 1))),
        ],
        annotator=annotator,
    )
    assert recs[0].kind is RecordKind.REQUEST
    assert "R200 = 1 (execute)" in recs[0].notes
    for rec in recs:
        assert rec.index == recs.index(rec)
