"""bench/proxy_floor.py, the least observer that the proxy's targets are judged
against, does the work it claims: every ADU framed however the chunks cut
them, every request paired with its answer, one JSON line per ADU, on mbmon's
own forwarding process (a real upstream on 127.0.0.1, stopped like Ctrl-C)."""

from __future__ import annotations

import importlib.util
import io
import signal
import struct
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import orjson
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.model import Chunk, Direction, Transport
from tests.proxy.test_proxy_e2e import ENV, ROOT, connect, expected_hr, fake, read_hr, rpc

FLOOR = ROOT / "bench" / "proxy_floor.py"


def _floor() -> ModuleType:
    spec = importlib.util.spec_from_file_location("proxy_floor_bench", FLOOR)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


floor = _floor()


def _conversation(n: int) -> list[tuple[int, Direction, bytes]]:
    """``n`` polls on each of two connections: (connection, direction, ADU)."""
    out = []
    for i in range(n):
        for conn in (0, 1):
            tid = (i * 7 + conn) & 0xFFFF
            out.append((conn, Direction.C2S, struct.pack(">HHHBBHH", tid, 0, 6, 1, 3, i, 2)))
            body = struct.pack(">BBHH", 3, 4, i, conn)
            out.append((conn, Direction.S2C, struct.pack(">HHHB", tid, 0, 7, 1) + body))
    return out


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 12),
    cuts=st.lists(st.integers(1, 40), min_size=1, max_size=30),
    holds=st.lists(st.booleans(), min_size=1, max_size=30),
)
def test_every_adu_is_framed_paired_and_logged_however_the_chunks_cut_them(
    n: int, cuts: list[int], holds: list[bool]
) -> None:
    """Chunks cut anywhere (ADUs split, several in one chunk, answers of one
    connection held back and sent together), in an order that could happen: a
    request has gone whole before its answer comes."""
    log = io.BytesIO()
    hub = floor.FloorHub("log", log)
    streams = [
        hub.new_stream(Transport.TCP, f"127.0.0.1:{4000 + c}", "127.0.0.1:502") for c in (0, 1)
    ]
    pieces: list[Chunk] = []
    held: dict[tuple[int, Direction], bytes] = {}
    k = 0

    def send(key: tuple[int, Direction]) -> None:
        nonlocal k
        data = held.pop(key, b"")
        while data:
            size = cuts[k % len(cuts)]
            k += 1
            pieces.append(Chunk(1.0 + len(pieces) / 1000, streams[key[0]], key[1], data[:size]))
            data = data[size:]

    for i, (conn, direction, raw) in enumerate(_conversation(n)):
        key = (conn, direction)
        held[key] = held.get(key, b"") + raw
        if direction is Direction.C2S or not holds[i % len(holds)]:
            send(key)
    for key in list(held):
        send(key)
    hub.submit(lambda: pieces[: len(pieces) // 2])
    hub.submit(lambda: pieces[len(pieces) // 2 :])
    assert hub.seen == len(pieces)
    assert hub.adus == 4 * n
    assert hub.pairs == 2 * n
    lines = [orjson.loads(line) for line in log.getvalue().splitlines()]
    assert len(lines) == 4 * n
    answers = [line for line in lines if line["dir"] == "s2c"]
    assert sorted((a["stream"], a["values"][0], a["values"][1]) for a in answers) == sorted(
        (c, i, c) for i in range(n) for c in (0, 1)
    )
    assert all(a["latency"] is not None and a["latency"] > 0 for a in answers)


def test_copies_stage_counts_chunks_and_decodes_nothing() -> None:
    hub = floor.FloorHub("copies")
    stream = hub.new_stream(Transport.TCP, "127.0.0.1:4000", "127.0.0.1:502")
    items = [Chunk(1.0, stream, d, raw) for conn, d, raw in _conversation(3) if conn == 0]
    hub.submit(lambda: items)
    assert (hub.seen, hub.adus, hub.pairs) == (len(items), 0, 0)


@pytest.mark.parametrize("where", [[], ["--inline"]], ids=["child", "inline"])
def test_the_floor_observer_serves_on_mbmons_forwarding(tmp_path: Path, where: list[str]) -> None:
    """Run as the benchmark runs it: listening line, answers through mbmon's engine
    (in its forwarding child, or in this process's loop with ``--inline``), the
    proxy's own summary and the floor's counts at Ctrl-C."""
    log = tmp_path / "floor.jsonl"
    with fake() as up:
        proc = subprocess.Popen(
            [
                sys.executable,
                str(FLOOR),
                "log",
                *where,
                "--upstream",
                f"127.0.0.1:{up.port}",
                "-w",
                str(log),
            ],
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
            cwd=tmp_path,
        )
        try:
            assert proc.stderr is not None
            line = proc.stderr.readline()
            assert line.startswith("listening on 127.0.0.1:"), line
            sock = connect(int(line.rsplit(":", 1)[1]))
            for tid in range(100):
                assert rpc(sock, tid, read_hr(tid, 3)) == expected_hr(tid, 1, tid, 3)
            sock.close()
        finally:
            proc.send_signal(signal.SIGINT)
            err = proc.communicate(timeout=20)[1]
    assert proc.returncode == 0, err
    assert "requests 100, responses 100" in err
    assert "not observed" not in err
    assert "floor log: ADUs framed 200, pairs 100" in err
    assert len(log.read_bytes().splitlines()) == 200
