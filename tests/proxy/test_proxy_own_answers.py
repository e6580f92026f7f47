"""An answer the proxy makes itself pairs with the request it answers.

``mbmon proxy`` as a real subprocess between a raw client and a real upstream on
127.0.0.1 that never answers (0x0B at ``--timeout``), a guard that refuses a
write (its exception), and an upstream nobody listens on (0x0A). In each case the
request and the proxy's answer are one transaction: the answer carries the
request's index and its latency and says it was made by the proxy; the request
is never reported unanswered and the answer never "(no matching request)". The
answer stays the proxy's, never the server's: its source is the proxy's listening
endpoint in the live JSON, in the MCAP log (read with the ``mcap`` reader), in
``replay --redecode`` and in the pcap ``export`` makes of it (read with tshark).
"""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from tests.proxy.test_proxy_answers import answering, mbap, no_answer, read_adu, start_upstream
from tests.proxy.test_proxy_e2e import ENV, Proxy

MADE = "made by the proxy"
READ = mbap(0x10, 1, bytes.fromhex("03 00 00 00 02"))  # R0..R1
WRITE = mbap(0x11, 1, bytes.fromhex("06 00 05 00 2A"))  # R5 = 42: refused
TIMEOUT = 0.3


def run_proxy(upstream_port: int, tmp: Path, client: Any) -> tuple[int, str]:
    """``mbmon proxy`` (records on stdout, ``-w own.mcap -w own.jsonl``) to
    ``upstream_port``; ``client(port)`` talks to it; the proxy's port and stdout."""
    p = Proxy(
        upstream_port,
        "--plain",
        "--timeout", str(TIMEOUT),
        "--deny-write", "hr:0-100",
        "-w", "own.mcap",
        "-w", "own.jsonl",
        tmp=tmp,
    )  # fmt: skip
    try:
        client(p.port)
    finally:
        out, err = p.stop()
    assert p.returncode == 0, err
    return p.port, out


def talk(port: int, *requests: bytes) -> list[bytes]:
    """Send each request and read its answer (one at a time)."""

    async def main() -> list[bytes]:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        got = []
        for request in requests:
            writer.write(request)
            got.append(await asyncio.wait_for(read_adu(reader), 10))
        writer.close()
        return got

    return asyncio.run(main())


def mcap_json(path: Path, topic: str) -> list[dict[str, Any]]:
    """The objects of ``topic``'s messages, read with the ``mcap`` package's reader
    (log format 3's protobuf messages decoded by their channel's encoding)."""
    from mcap.reader import make_reader

    from mbmon.io.mcap.proto import decode_payload

    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        return [
            decode_payload(s.name if s else "", ch.message_encoding, m.data)
            for s, ch, m in reader.iter_messages()
            if ch.topic == topic
        ]


def check_paired(records: list[dict[str, Any]], tid: int, code: int, proxy_at: str) -> None:
    """The request ``tid`` and the proxy's exception ``code`` are one transaction."""
    (request,) = [r for r in records if r.get("kind") == "request" and r["tid"] == tid]
    (answer,) = [r for r in records if r.get("kind") == "exception" and r["tid"] == tid]
    assert answer["exception_code"] == code
    assert answer["request_index"] == request["index"], (request, answer)
    assert answer["latency_ms"] is not None and answer["latency_ms"] >= 0
    assert MADE in answer["notes"], answer
    assert answer["src"] == proxy_at and answer["dst"] == request["src"]
    assert MADE not in request["notes"]
    # never reported unanswered
    timeouts = [r for r in records if r.get("event") == "timeout"]
    assert all(r.get("info", {}).get("request_index") != request["index"] for r in timeouts)


def exported_rows(tmp: Path, proxy_port: int) -> list[tuple[int, int, int, int, str]]:
    """``export own.mcap -o own.pcap``, read back by tshark (the proxy's port decoded as
    Modbus/TCP too): (source port, destination port, transaction id, function code,
    exception code) of every Modbus/TCP PDU."""
    out = subprocess.run(
        [sys.executable, "-m", "mbmon", "export", "own.mcap", "-o", "own.pcap"],
        cwd=tmp, env=ENV, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    fields = ["tcp.srcport", "tcp.dstport", "mbtcp.trans_id", "modbus.func_code"]
    fields.append("modbus.exception_code")
    shark = subprocess.run(
        ["tshark", "-r", str(tmp / "own.pcap"), "-d", f"tcp.port=={proxy_port},mbtcp",
         "-Y", "mbtcp", "-T", "fields",
         *(x for f in fields for x in ("-e", f))],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert shark.returncode == 0, shark.stderr
    rows = []
    for line in shark.stdout.splitlines():
        sport, dport, tid, fc, exc = (line.split("\t") + [""] * 5)[:5]
        rows.append((int(sport), int(dport), int(tid), int(fc), exc))
    return rows


def replayed(tmp: Path) -> list[dict[str, Any]]:
    """``replay own.mcap --redecode --json``: the log's raw bytes decoded again."""
    out = subprocess.run(
        [sys.executable, "-m", "mbmon", "replay", "own.mcap", "--redecode", "--json"],
        cwd=tmp, env=ENV, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    return [json.loads(line) for line in out.stdout.splitlines() if line.strip()]


def check_everywhere(tmp: Path, out: str, proxy_port: int, answered: dict[int, int]) -> None:
    """Each request of ``answered`` (tid -> the proxy's exception code) pairs with its
    answer on the screen, in the JSON log, in the MCAP log and once decoded again;
    the answers come from the proxy's port in the exported pcap."""
    proxy_at = f"127.0.0.1:{proxy_port}"
    lines = [line for line in out.splitlines() if f"{proxy_at} →" in line]
    assert len(lines) == len(answered), out
    for line in lines:
        assert MADE in line and " ms)" in line and "no matching request" not in line, line
    assert "No response" not in out, out
    live = [json.loads(line) for line in (tmp / "own.jsonl").read_text().splitlines()]
    logged = mcap_json(tmp / "own.mcap", "/modbus/frames")
    logged += mcap_json(tmp / "own.mcap", "/mbmon/events")
    again = replayed(tmp)
    for records in (live, logged, again):
        for tid, code in answered.items():
            check_paired(records, tid, code, proxy_at)
    monitor = [m["message"] for m in mcap_json(tmp / "own.mcap", "/modbus/monitor")]
    assert sum(MADE in m for m in monitor) == len(answered)
    if shutil.which("tshark") is None:
        pytest.skip("tshark not installed: the exported pcap was not checked")
    rows = exported_rows(tmp, proxy_port)
    for tid, code in answered.items():
        (answer,) = [r for r in rows if r[2] == tid and r[4]]
        assert answer[0] == proxy_port and int(answer[4]) == code, rows


def test_a_gateway_timeout_and_a_guard_refusal_pair_with_their_requests(
    tmp_path: Path,
) -> None:
    """A real upstream that never answers: 0x0B at the timeout; a refused write: the
    guard's exception 01. Both pair with their requests, marked as the proxy's."""

    async def upstream() -> tuple[asyncio.Server, int]:
        return await start_upstream(answering(no_answer))

    loop = asyncio.new_event_loop()
    server, port = loop.run_until_complete(upstream())
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    try:
        answers: list[bytes] = []
        proxy_port, out = run_proxy(
            port, tmp_path, lambda at: answers.extend(talk(at, READ, WRITE))
        )
    finally:
        loop.call_soon_threadsafe(server.close)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
    assert answers == [
        mbap(0x10, 1, bytes.fromhex("83 0B")),
        mbap(0x11, 1, bytes.fromhex("86 01")),
    ]
    check_everywhere(tmp_path, out, proxy_port, {0x10: 0x0B, 0x11: 0x01})


def test_an_unreachable_upstream_answer_pairs_with_its_request(tmp_path: Path) -> None:
    """Nobody listens upstream: 0x0A at once, paired with its request."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: connections are refused
    answers: list[bytes] = []
    proxy_port, out = run_proxy(port, tmp_path, lambda at: answers.extend(talk(at, READ)))
    assert answers == [mbap(0x10, 1, bytes.fromhex("83 0A"))]
    check_everywhere(tmp_path, out, proxy_port, {0x10: 0x0A})


def test_the_pipeline_pairs_a_joined_streams_answers_with_the_other_streams_requests() -> None:
    """The contract under the above, byte for byte: a CONNECT whose info has
    ``answers_on`` joins that stream to its own pairing, and the answers there carry
    its ``note``; after its DISCONNECT the other stream pairs on its own again."""
    from mbmon.model import Chunk, Direction, Event, EventKind, RecordKind, Stream, Transport
    from mbmon.pipeline import Pipeline, PipelineConfig

    client = Stream(1, Transport.TCP, "10.0.0.9:40000", "10.0.0.1:502")
    own = Stream(2, Transport.TCP, "10.0.0.9:40000", "127.0.0.1:1502")
    pipe = Pipeline(config=PipelineConfig(timeout=5.0))
    gateway = mbap(0x10, 1, bytes.fromhex("83 0B"))
    out = [
        *pipe.feed(Event(99.0, client, EventKind.CONNECT, {"answers_on": 2, "note": MADE})),
        *pipe.feed(Chunk(100.0, client, Direction.C2S, READ)),
        *pipe.feed(Chunk(100.5, own, Direction.S2C, gateway)),
        *pipe.feed(Event(101.0, client, EventKind.DISCONNECT, {"how": "fin", "by": "client"})),
        *pipe.feed(Chunk(102.0, client, Direction.C2S, READ)),
        *pipe.feed(Chunk(102.1, own, Direction.S2C, gateway)),
    ]
    frames = [r for r in out if r.frame is not None]
    request, answer, again, stray = frames
    assert answer.kind is RecordKind.EXCEPTION and answer.stream is own
    assert (answer.request_index, answer.latency) == (request.index, 0.5)
    assert answer.notes == (MADE,) and request.notes == ()
    # parted: the same bytes on the proxy's stream answer nothing now, unmarked
    assert stray.request is None and stray.notes == ()
    assert again.kind is RecordKind.REQUEST
