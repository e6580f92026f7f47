"""A guard refusal held behind an answer half-way to the client (docs/proxy.md,
"Answers reach the client whole") is written when that answer is whole, which may
be after the pipeline's pairing window: its request is then reported unanswered
("No response"), and the refusal, when it comes, is logged as the late answer to
that request (its latency, its request's index, the note ``late: ...``), never as an
answer that matches no request.

Real parts: the pipeline fed as the proxy's observation feeds it (a byte table of
chunks and events), and ``mbmon proxy`` between a real client socket and an
upstream on 127.0.0.1 that streams its answer a byte every 0.4 s, its log read back."""

from __future__ import annotations

import json
from pathlib import Path

from mbmon.format import View, record_line
from mbmon.model import Chunk, Direction, Event, EventKind, RecordKind, Stream, Transport
from mbmon.pipeline import LATE_NOTE, Pipeline, PipelineConfig
from tests.proxy.test_proxy_answers import SLOW_ANSWER
from tests.proxy.test_proxy_whole_answers import REFUSAL, WRITE, exchange

CLIENT = Stream(0, Transport.TCP, "127.0.0.1:40000", "127.0.0.1:502")
OWN = Stream(1, Transport.TCP, "127.0.0.1:40000", "proxy 127.0.0.1:1502")
READ = bytes.fromhex("00 1C 00 00 00 06 FF 03 01 73 00 01")


def _records(late: float) -> list:
    """A read answered byte by byte; a write refused at 0.1 s whose refusal is written
    ``late`` s later (with the read's last byte)."""
    pipe = Pipeline(None, PipelineConfig(timeout=1.2))
    connect = Event(0.0, CLIENT, EventKind.CONNECT, {"answers_on": 1, "note": "made by the proxy"})
    out = list(pipe.feed(connect))
    out += pipe.feed(Chunk(0.01, CLIENT, Direction.C2S, READ))
    out += pipe.feed(Chunk(0.02, CLIENT, Direction.S2C, SLOW_ANSWER[:3]))
    out += pipe.feed(Chunk(0.1, OWN, Direction.C2S, WRITE))
    t = 0.2
    while t < 0.1 + late:
        out += pipe.tick(t)
        t += 0.1
    out += pipe.feed(Chunk(0.1 + late, CLIENT, Direction.S2C, SLOW_ANSWER[3:]))
    out += pipe.feed(Chunk(0.1 + late, OWN, Direction.S2C, REFUSAL))
    out += pipe.finish()
    return out


def test_a_refusal_written_after_the_pairing_window_is_its_requests_late_answer() -> None:
    records = _records(late=2.0)
    request = next(r for r in records if r.frame is not None and r.frame.raw == WRITE)
    timeouts = [
        r
        for r in records
        if r.event is not None
        and r.event.kind is EventKind.TIMEOUT
        and r.event.info["request_index"] == request.index
    ]
    assert len(timeouts) == 1  # the refused write, at 1.3 s: reported unanswered
    answer = next(r for r in records if r.frame is not None and r.frame.raw == REFUSAL)
    assert answer.kind is RecordKind.EXCEPTION
    assert answer.request is request.frame
    assert answer.request_index == request.index
    assert answer.latency is not None and abs(answer.latency - 2.0) < 1e-9
    assert answer.notes == ("made by the proxy", LATE_NOTE)
    line = record_line(answer, View())
    assert "(no matching request)" not in line
    assert line.endswith(f"made by the proxy; {LATE_NOTE} (2000.0 ms)")


def test_a_refusal_within_the_window_is_answered_as_ever() -> None:
    records = _records(late=0.5)
    assert not [r for r in records if r.event is not None and r.event.kind is EventKind.TIMEOUT]
    assert "(no matching request)" not in "".join(record_line(r, View()) for r in records)
    answer = next(r for r in records if r.frame is not None and r.frame.raw == REFUSAL)
    assert answer.notes == ("made by the proxy",)
    assert answer.latency is not None and abs(answer.latency - 0.5) < 1e-9


def test_an_answer_of_the_proxys_that_matches_nothing_stays_unsolicited() -> None:
    pipe = Pipeline(None, PipelineConfig(timeout=1.2))
    connect = Event(0.0, CLIENT, EventKind.CONNECT, {"answers_on": 1, "note": "made by the proxy"})
    out = list(pipe.feed(connect))
    out += pipe.feed(Chunk(0.1, OWN, Direction.C2S, WRITE))
    out += pipe.tick(5.0)
    other = bytes.fromhex("00 1E 00 00 00 03 FF 86 01")  # another tid: not its answer
    out += pipe.feed(Chunk(6.0, OWN, Direction.S2C, other))
    answer = out[-1]
    assert answer.request is None and answer.latency is None
    assert record_line(answer, View()).endswith("(no matching request)")


def test_mbmon_proxy_logs_a_refusal_held_past_the_window_as_its_late_answer(
    tmp_path: Path,
) -> None:
    """The upstream streams the read's answer a byte every 0.4 s (4.4 s: within the
    two --timeouts a streamed answer may take); the write, sent after its first byte,
    is refused at once and answered after the last one, about 4.3 s later: past the
    pairing window (--timeout 2.5, plus 1 s)."""
    log = tmp_path / "seen.jsonl"
    args = ["--deny-write", "hr:0-100", "--timeout", "2.5", "-w", str(log)]
    got = exchange(tmp_path, False, 0.4, args, WRITE, 1)
    assert got == SLOW_ANSWER + REFUSAL
    records = [json.loads(line) for line in log.read_text().splitlines()]
    refused = [r for r in records if r.get("pdu") == "06 00 05 00 2A"]
    assert len(refused) == 1, records
    timeouts = [r for r in records if r.get("event") == "timeout"]
    assert refused[0]["index"] in [t["info"]["request_index"] for t in timeouts]
    answer = [r for r in records if r.get("pdu") == "86 01"]
    assert len(answer) == 1, records
    assert answer[0]["request_index"] == refused[0]["index"]
    assert answer[0]["latency_ms"] > 3500
    assert LATE_NOTE in answer[0]["notes"]
    assert "no matching request" not in answer[0]["line"]
