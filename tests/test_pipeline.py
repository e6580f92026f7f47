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


# ---------------------------------------------------------------- time, damage, memory

RTU_REQ = encode_rtu(1, encode_read_request(3, 0, 2))


def test_rtu_request_without_answer_is_unanswered_at_timeout_by_tick() -> None:
    # no further bytes, only time; the bus goes quiet after the request
    pipe = Pipeline(None, PipelineConfig(timeout=1.0))
    recs = pipe.feed(Chunk(10.0, BUS, Direction.BUS, RTU_REQ))
    assert [r.kind for r in recs] == [RecordKind.REQUEST]
    assert pipe.next_deadline() == 11.0
    assert pipe.tick(10.9) == []
    [t] = pipe.tick(11.0)
    assert t.event is not None and t.event.kind is EventKind.TIMEOUT
    assert (t.ts, t.event.info["request_index"]) == (11.0, 0)
    assert pipe.next_deadline() is None
    assert pipe.finish() == []


def test_rtu_bytes_held_are_settled_by_tick() -> None:
    pipe = Pipeline(None, PipelineConfig(timeout=1.0, silence=0.2))
    recs = pipe.feed(Chunk(10.0, BUS, Direction.BUS, RTU_REQ + RTU_REQ[:4]))
    assert [r.kind for r in recs] == [RecordKind.REQUEST]
    assert pipe.next_deadline() == 10.2
    [n] = pipe.tick(10.2)
    assert n.kind is RecordKind.NOISE and n.noise is not None
    assert (n.noise.raw, n.ts) == (RTU_REQ[:4], 10.0)
    assert pipe.next_deadline() == 11.0  # now only the request's timeout


def test_rtu_user_defined_request_settled_then_timed_out_by_ticks() -> None:
    user = encode_rtu(5, bytes([0x41, 1, 2, 3]))
    pipe = Pipeline(None, PipelineConfig(timeout=1.0, silence=0.1))
    recs = pipe.feed(Chunk(1.0, BUS, Direction.BUS, user))
    recs += pipe.tick(1.1)
    recs += pipe.tick(2.0)
    kinds = [(r.kind, r.event.kind if r.event else None) for r in recs]
    assert (RecordKind.REQUEST, None) in kinds
    assert kinds[-1] == (RecordKind.EVENT, EventKind.TIMEOUT)


def test_no_made_up_timeouts_after_source_damage() -> None:
    # the capture is cut off after two requests
    pipe = Pipeline(None, PipelineConfig(timeout=1.0))
    recs = pipe.feed(c2s(TCP, 1.0, encode_adu(1, 1, encode_read_request(3, 0, 1))))
    recs += pipe.feed(c2s(TCP, 1.5, encode_adu(2, 1, encode_read_request(3, 0, 1))))
    recs += pipe.feed(Event(1.6, None, EventKind.ERROR, {"message": "truncated capture"}))
    recs += pipe.finish(5.0)
    kinds = [r.event.kind for r in recs if r.event is not None]
    assert kinds == [EventKind.ERROR]
    assert pipe.counts["timeouts"] == 0
    assert pipe._pending_index == {}


def test_requests_expired_before_damage_are_still_reported() -> None:
    pipe = Pipeline(None, PipelineConfig(timeout=1.0, tick_every=10.0))
    recs = pipe.feed(c2s(TCP, 1.0, encode_adu(1, 1, encode_read_request(3, 0, 1))))
    recs += pipe.feed(c2s(TCP, 1.0, encode_adu(2, 1, encode_read_request(3, 0, 1))))
    recs += pipe.feed(c2s(TCP, 2.5, encode_adu(3, 1, encode_read_request(3, 0, 1))))
    recs += pipe.feed(Event(2.6, None, EventKind.ERROR, {"message": "damaged record"}))
    recs += pipe.finish(9.0)
    timeouts = [r for r in recs if r.event is not None and r.event.kind is EventKind.TIMEOUT]
    assert [t.event.info["tid"] for t in timeouts] == [1, 2]  # not 3: cut off


def test_rtu_broadcast_leaves_no_pending_index() -> None:
    pipe = Pipeline(None)
    for i in range(100):
        pipe.feed(Chunk(float(i), BUS, Direction.BUS, encode_rtu(0, encode_write_single(6, i, i))))
    assert pipe._pending_index == {}


def test_disconnect_releases_stream_state() -> None:
    pipe = Pipeline(None)
    for sid in range(50):
        s = Stream(sid, Transport.TCP, f"10.0.0.1:{40000 + sid}", "10.0.0.2:502")
        pipe.feed(c2s(s, 1.0, encode_adu(1, 1, encode_read_request(3, 0, 1))[:9]))
        pipe.feed(Event(1.1, s, EventKind.DISCONNECT, {"how": "fin"}))
    assert pipe._decoders == {} and pipe._streams == {} and pipe._waiting == {}


def test_idle_streams_are_flushed_and_forgotten_in_tick() -> None:
    pipe = Pipeline(None, PipelineConfig(idle_timeout=60.0))
    recs = pipe.feed(c2s(TCP, 1.0, encode_adu(1, 1, encode_read_request(3, 0, 1))[:9]))
    recs += pipe.feed(c2s(UDP, 50.0, encode_adu(1, 1, encode_read_request(3, 0, 1))))
    recs += pipe.tick(30.0)
    assert (TCP.id, Direction.C2S) in pipe._decoders
    recs += pipe.tick(70.0)
    assert (TCP.id, Direction.C2S) not in pipe._decoders and TCP.id not in pipe._streams
    assert (UDP.id, Direction.C2S) in pipe._decoders  # active 20 s ago
    noise = [r for r in recs if r.kind is RecordKind.NOISE]
    assert len(noise) == 1 and noise[0].ts == 1.0 and len(noise[0].noise.raw) == 9


def test_pending_requests_are_bounded_over_all_streams() -> None:
    pipe = Pipeline(None, PipelineConfig(max_pending=800))
    timeouts = 0
    for sid in range(5000):
        s = Stream(sid, Transport.TCP, f"10.0.0.1:{sid}", "10.0.0.2:502")
        for r in pipe.feed(c2s(s, 1.0, encode_adu(1, 1, encode_read_request(3, 0, 1)))):
            timeouts += r.event is not None and r.event.kind is EventKind.TIMEOUT
        assert pipe.pairer.pending_count <= 800
        assert len(pipe._pending_index) == pipe.pairer.pending_count
    assert timeouts >= 5000 - 800
    assert pipe.pairer.pending_count == sum(len(p) for p in pipe.pairer._pending.values())


class _TickingAnnotator:
    """An annotator with the optional tick/next_deadline of mbmon.semantics."""

    def __init__(self) -> None:
        self.ticks: list[float] = []

    def annotate(self, tx):  # type: ignore[no-untyped-def]
        from mbmon.model import Annotation

        return Annotation()

    def tick(self, now: float):  # type: ignore[no-untyped-def]
        from mbmon.model import CommandUpdate, Phase

        self.ticks.append(now)
        return [CommandUpdate(now, TCP, 1, Phase.WARNING, "never completed")]

    def next_deadline(self) -> float:
        return 42.0


def test_tick_reaches_the_annotator() -> None:
    ann = _TickingAnnotator()
    pipe = Pipeline(ann)  # type: ignore[arg-type]
    assert pipe.next_deadline() == 42.0
    [rec] = pipe.tick(42.0)
    assert rec.kind is RecordKind.COMMAND and rec.command is not None
    assert rec.command.text == "never completed" and ann.ticks == [42.0]


_MEMORY_CHILD = r"""
import resource, sys
from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.pipeline import Pipeline, PipelineConfig
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response

n, unanswered = int(sys.argv[1]), int(sys.argv[2])
pipe = Pipeline(None, PipelineConfig(max_pending=5_000))
req = encode_adu(1, 1, encode_read_request(3, 0, 2))
resp = encode_adu(1, 1, encode_read_response(3, [1, 2]))
for i in range(n):
    s = Stream(i, Transport.TCP, f"10.{i >> 8 & 255}.{i & 255}.1:{i >> 16}", "10.0.0.1:502")
    ts = i * 0.001
    pipe.feed(Event(ts, s, EventKind.CONNECT, {}))
    pipe.feed(Chunk(ts, s, Direction.C2S, req))
    pipe.feed(Chunk(ts, s, Direction.S2C, resp))
    pipe.feed(Event(ts, s, EventKind.DISCONNECT, {"how": "fin"}))
for i in range(unanswered):  # all at one timestamp, each on its own connection
    s = Stream(n + i, Transport.TCP, f"11.{i >> 8 & 255}.{i & 255}.1:{i >> 16}", "10.0.0.1:502")
    pipe.feed(Chunk(1e6, s, Direction.C2S, req))
    pipe.feed(Event(1e6, s, EventKind.DISCONNECT, {"how": "rst"}))
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def test_memory_stays_flat_over_many_short_streams() -> None:
    # week-long runs. Peak RSS of a child at two sizes (5x apart).
    import subprocess
    import sys
    from pathlib import Path

    root = str(Path(__file__).resolve().parents[1])

    def peak_kb(n: int, unanswered: int) -> int:
        done = subprocess.run(
            [sys.executable, "-c", _MEMORY_CHILD, str(n), str(unanswered)],
            capture_output=True,
            text=True,
            check=True,
            env={"PYTHONPATH": root, "PATH": "/usr/bin:/bin"},
        )
        return int(done.stdout.strip())

    small = peak_kb(8_000, 8_000)
    large = peak_kb(40_000, 40_000)
    assert large - small < 8_000, (small, large)  # KiB: flat, not 5x


def test_short_garbage_reply_is_one_noise_record_when_it_arrived() -> None:
    # a short garbage reply, through the pipeline: no second record at the connection's end
    recs = run(
        [
            c2s(TCP, 1.0, encode_adu(1, 1, encode_read_request(3, 0, 1))),
            s2c(TCP, 1.01, bytes.fromhex("DE AD BE EF 12 34 56")),
            Event(30.0, TCP, EventKind.DISCONNECT, {"how": "fin"}),
        ]
    )
    noise = [r for r in recs if r.kind is RecordKind.NOISE]
    assert len(noise) == 1 and noise[0].ts == 1.01 and len(noise[0].noise.raw) == 7


def test_http_bytes_on_502_make_no_frame_and_no_made_up_timeout() -> None:
    # HTTP on port 502, through the pipeline: was "Function 0x41" then "No response"
    http = (
        b"GET / HTTP/1.1\r\nHost: x\r\nX-Pad: "
        + bytes.fromhex("00 00 00 00 00 04 07 41 42 43")
        + b"\r\n\r\n"
    )
    recs = run([c2s(TCP, 1.0, http), Event(9.0, TCP, EventKind.DISCONNECT, {"how": "fin"})])
    assert [(r.kind, r.ts) for r in recs] == [(RecordKind.EVENT, 9.0), (RecordKind.NOISE, 1.0)]
    assert recs[1].noise is not None and recs[1].noise.raw == http
    assert not any(r.event is not None and r.event.kind is EventKind.TIMEOUT for r in recs)
