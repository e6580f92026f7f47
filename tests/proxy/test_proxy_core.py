"""The proxy's observation on the compiled core (:mod:`mbmon.core.chunks`) against the
reference pipeline, byte for byte: the pipe bytes of a real proxy (its forwarding
child between a real upstream and real clients on 127.0.0.1) and generated ones
(every function code, splits at every byte, timeouts, the hand-overs), cut into
the same reads with the same ticks (harness: ``core_diff.py``); and ``mbmon proxy``
itself on the core against ``MBMON_NO_EXTENSIONS=1`` on the same traffic."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbmon.model import Transport
from mbmon.protocol.pdu import encode_exception, encode_read_request, encode_read_response
from tests.core.gen import every_function_pair
from tests.core.mcap_diff import log_contents
from tests.proxy import core_diff as cd
from tests.proxy.test_proxy_e2e import (
    ENV,
    adu,
    connect,
    exception,
    fake,
    free_port,
    read_adu,
    read_hr,
    rpc,
    wait_port,
)

try:
    from mbmon.core import _load

    _WHY = _load()
except ImportError as exc:  # pragma: no cover
    _WHY = str(exc)

pytestmark = pytest.mark.skipif(
    _WHY is not None and os.environ.get("MBMON_REQUIRE_CORE") != "1",
    reason=f"the compiled core is not built: {_WHY}",
)

ROOT = Path(__file__).resolve().parents[2]


def same(
    steps: list[cd.Step],
    *,
    handed: bool | str | None = False,
    tmp: Path | None = None,
    **kw: object,
) -> bytes:
    """Both wirings print the same bytes, text and JSON; with ``tmp``, they also write
    the same ``-w x.mcap`` log, quiet and with each console; ``handed``: whether the
    core must hand over (False: it must not; a string: the reason must contain it)."""
    got = b""
    consoles: tuple[bool | None, ...] = (False, True) if tmp is None else (None, False, True)
    for n, as_json in enumerate(consoles):
        logs = (None, None) if tmp is None else (tmp / f"ref{n}.mcap", tmp / f"core{n}.mcap")
        want = cd.reference(steps, as_json=as_json, log=logs[0], **kw)  # type: ignore[arg-type]
        out, why = cd.core(steps, as_json=as_json, log=logs[1], **kw)  # type: ignore[arg-type]
        assert out == want, (as_json, why)
        if logs[0] is not None and logs[1] is not None:
            want_log, got_log = log_contents(logs[0]), log_contents(logs[1])
            pairs = zip(got_log["messages"], want_log["messages"], strict=False)
            for i, (a, b) in enumerate(pairs):
                assert a == b, f"message {i} ({as_json})"
            assert got_log == want_log, as_json
            assert len(got_log["messages"]) > 10
        if handed is False:
            assert why is None, why
        elif isinstance(handed, str):
            assert why is not None and handed in why, why
        got = out or got
    assert got, "nothing printed"
    return got


# --------------------------------------------------------------------------- generated


def _session(t0: float = 1000.0) -> list[cd.Step]:
    """One client: every function code's request and answer, one chunk each."""
    steps: list[cd.Step] = [cd.client(0, t0, 40000)]
    t = t0
    for tid, (req, resp) in enumerate(every_function_pair()):
        t += 0.01
        steps.append(cd.chunk(0, cd.C2S, t, adu(tid, 1, req)))
        steps.append(cd.chunk(0, cd.S2C, t + 0.002, adu(tid, 1, resp)))
    steps.append(cd.event(t + 0.1, 0, "disconnect", {"how": "fin", "by": "client"}))
    return steps


def test_every_function_code_is_the_references(tmp_path: Path) -> None:
    same(cd.with_ticks([b"".join(_session())]), tmp=tmp_path)


def test_timeouts_late_answers_and_unsolicited_ones_are_the_references(tmp_path: Path) -> None:
    t = 50.0
    data = [
        cd.client(0, t, 40001),
        cd.chunk(0, cd.C2S, t + 0.1, adu(1, 1, encode_read_request(3, 0, 2))),
        cd.chunk(0, cd.C2S, t + 0.2, adu(2, 1, encode_read_request(4, 0, 2))),
    ]
    late = [
        cd.chunk(0, cd.S2C, t + 9.0, adu(1, 1, encode_read_response(3, [1, 2]))),
        cd.chunk(0, cd.S2C, t + 9.1, adu(7, 2, encode_exception(3, 2))),
        cd.event(t + 9.5, -1, "notice", {"message": "a notice of no stream"}),
        cd.event(t + 9.6, 0, "disconnect", {"how": "fin", "by": "client"}),
    ]
    steps: list[cd.Step] = [b"".join(data), t + 1.0, t + 5.15, b"".join(late), t + 20.0]
    same(steps, tmp=tmp_path)


@pytest.mark.parametrize("direction", [cd.C2S, cd.S2C])
def test_an_adu_cut_at_every_byte_is_the_references(direction: int) -> None:
    req = adu(5, 1, encode_read_request(3, 100, 10))
    resp = adu(5, 1, encode_read_response(3, list(range(10))))
    whole = req if direction == cd.C2S else resp
    for cut in range(1, len(whole)):
        t = 10.0
        head = [cd.client(0, t, 40002)]
        if direction == cd.S2C:
            head.append(cd.chunk(0, cd.C2S, t + 0.01, req))
        parts = [
            cd.chunk(0, direction, t + 0.02, whole[:cut]),
            cd.chunk(0, direction, t + 0.03, whole[cut:]),
        ]
        if direction == cd.C2S:
            parts.append(cd.chunk(0, cd.S2C, t + 0.04, resp))
        parts.append(cd.event(t + 0.05, 0, "disconnect", {"how": "fin", "by": "client"}))
        same([b"".join(head), t + 0.015, b"".join(parts), t + 1.0])


def test_the_proxys_own_answers_hand_the_run_over(tmp_path: Path) -> None:
    t = 20.0
    steps: list[cd.Step] = [
        cd.client(0, t, 40003)
        + cd.chunk(0, cd.C2S, t + 0.1, adu(1, 1, encode_read_request(3, 0, 1)))
        + cd.chunk(0, cd.S2C, t + 0.2, adu(1, 1, encode_read_response(3, [7]))),
        # a refused write: request and the proxy's answer on the proxy's own stream
        cd.chunk(1, cd.C2S, t + 0.3, adu(2, 1, bytes.fromhex("06000a0001")))
        + cd.chunk(1, cd.S2C, t + 0.3, adu(2, 1, encode_exception(6, 1)))
        + cd.event(t + 0.3, 0, "guard", {"message": "refused", "rule": "read-only"})
        + cd.chunk(0, cd.C2S, t + 0.4, adu(3, 1, encode_read_request(3, 0, 1)))
        + cd.chunk(0, cd.S2C, t + 0.5, adu(3, 1, encode_read_response(3, [8])))
        + cd.event(t + 0.6, 0, "disconnect", {"how": "fin", "by": "client"}),
        t + 10.0,
    ]
    same(steps, handed="own answers", tmp=tmp_path)


def test_noise_hands_the_run_over_with_the_bytes_held(tmp_path: Path) -> None:
    t = 30.0
    req = adu(1, 1, encode_read_request(3, 0, 1))
    steps: list[cd.Step] = [
        cd.client(0, t, 40004)
        + cd.chunk(0, cd.C2S, t + 0.1, req[:4])  # held by the core, exported
        + cd.chunk(0, cd.C2S, t + 0.2, req[4:] + b"\xff\xff\xff\x00\x01\x02\x03\x04"),
        t + 0.5,
        cd.chunk(0, cd.C2S, t + 0.6, adu(2, 1, encode_read_request(3, 0, 1)))
        + cd.event(t + 0.7, 0, "disconnect", {"how": "fin", "by": "client"}),
        t + 10.0,
    ]
    same(steps, handed="noise", tmp=tmp_path)


def test_an_incomplete_adu_at_a_disconnect_hands_the_run_over(tmp_path: Path) -> None:
    t = 40.0
    req = adu(1, 1, encode_read_request(3, 0, 1))
    steps: list[cd.Step] = [
        cd.client(0, t, 40005)
        + cd.client(2, t, 40006)
        + cd.chunk(2, cd.C2S, t + 0.05, req)
        + cd.chunk(0, cd.C2S, t + 0.1, req[:5])
        + cd.event(t + 0.2, 0, "disconnect", {"how": "reset", "by": "client"})
        + cd.chunk(2, cd.S2C, t + 0.3, adu(1, 1, encode_read_response(3, [3]))),
        t + 10.0,
    ]
    same(steps, handed="incomplete ADU", tmp=tmp_path)


def test_a_second_client_makes_every_label_name_its_peer(tmp_path: Path) -> None:
    """With the robot the upstream, labels name the client once a second one is seen,
    those of a stream labelled before it too (the view relabels; so does the core)."""
    t = 60.0
    read, answer = encode_read_request(3, 0, 1), encode_read_response(3, [5])
    data = [cd.client(0, t, 40010)]
    for i in range(3):
        data.append(cd.chunk(0, cd.C2S, t + 0.1 * i, adu(i, 1, read)))
        data.append(cd.chunk(0, cd.S2C, t + 0.1 * i + 0.01, adu(i, 1, answer)))
        if i == 0:
            data.append(cd.client(2, t + 0.05, 40011))
            data.append(cd.chunk(2, cd.C2S, t + 0.06, adu(9, 1, read)))
            data.append(cd.chunk(2, cd.S2C, t + 0.07, adu(9, 1, answer)))
    data.append(cd.event(t + 1.0, 0, "disconnect", {"how": "fin", "by": "client"}))
    data.append(cd.event(t + 1.0, 2, "disconnect", {"how": "fin", "by": "client"}))
    steps: list[cd.Step] = [b"".join(data), t + 10.0]
    same(steps, tmp=tmp_path)
    lines = cd.reference(steps, as_json=False).decode().splitlines()
    assert "Receive from client  [u1 t0]" in lines[1]
    assert sum("Receive from client 127.0.0.1:40010" in line for line in lines) == 2


def test_ended_streams_are_released_once_nothing_waits() -> None:
    """Client after client: the core keeps the state of open streams only; one that
    ended with a request pending keeps it until the request times out."""
    from mbmon.core.chunks import ChunkCore
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig

    hub = Hub(Pipeline(None, PipelineConfig(timeout=4.0)), clock=lambda: 0.0)
    stage = ChunkCore(timeout=4.0, view=View(), as_json=False, write=None, pipeline=hub.pipeline)
    read, answer = encode_read_request(3, 0, 1), encode_read_response(3, [5])
    t = 1.0
    for k in range(50):
        sid = 2 * k
        t += 0.01
        got = stage.take(
            [
                ("stream", sid, hub.new_stream(Transport.TCP, f"c:{k}", "s:502")),
                ("stream", sid + 1, hub.new_stream(Transport.TCP, f"c:{k}", "proxy")),
                ("event", t, sid, "connect", {"answers_on": sid + 1}),
                cd.chunk(sid, cd.C2S, t, adu(1, 1, read))
                + cd.chunk(sid, cd.S2C, t, adu(1, 1, answer))
                + cd.chunk(sid, cd.C2S, t, adu(2, 1, read) if k == 49 else b""),
                ("event", t, sid, "disconnect", {"how": "fin", "by": "client"}),
            ]
        )
        assert got == []
    assert stage.handed is None
    assert stage._core.streams_held() == 1  # the last: a request still pending
    assert len(stage.streams) == 0
    stage.tick(t + 1.0)
    assert stage._core.streams_held() == 1
    stage.tick(t + 5.0)  # it times out: released
    assert stage._core.streams_held() == 0
    assert stage.counts()["timeouts"] == 1


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(min_value=1, max_value=1 << 20), max_size=12))
def test_any_cut_of_the_pipe_is_the_references(cuts: list[int]) -> None:
    steps = cd.with_ticks([b"".join(_session())])
    assert cd.core(cd.recut(steps, cuts), as_json=True)[0] == cd.reference(steps, as_json=True)


# --------------------------------------------------------------------------- a real proxy


def _traffic(port: int, mode: str) -> None:
    """Two clients one after the other, reads, writes and an exception; a refused
    write under the guard."""
    for n in range(2):
        sock = connect(port)
        for tid in range(20):
            rpc(sock, tid, read_hr(tid, 1 + tid % 5), unit=1 + n)
        rpc(sock, 30, bytes.fromhex("0600640007"))
        rpc(sock, 31, bytes.fromhex("2b0e0100"))
        if mode == "guard":
            assert rpc(sock, 32, bytes.fromhex("0600650007")) == exception(32, 6, 1)
            rpc(sock, 33, read_hr(0, 2))
        sock.close()
        time.sleep(0.05)


@pytest.mark.parametrize("mode", ["plain", "guard"])
def test_a_real_proxys_pipe_is_the_references(mode: str, tmp_path: Path) -> None:
    from mbmon.proxy.guard import Guard

    config = {"guard": Guard(read_only=True)} if mode == "guard" else {}
    with fake() as up, cd.Recording(up.port, **config) as rec:
        _traffic(rec.port, mode)
        time.sleep(0.3)
    reads = rec.reads
    steps = cd.with_ticks(reads)
    handed = "own answers" if mode == "guard" else False
    text = same(steps, handed=handed, upstream=rec.upstream, tmp=tmp_path)
    assert text.count(b"Read Holding Registers") >= 80
    # the same bytes in other reads: one record at a time, and all at once
    joined = b"".join(reads)
    one = cd.with_ticks([joined])
    same(one, handed=handed, upstream=rec.upstream)


# --------------------------------------------------------------------------- mbmon proxy


def _run_proxy(upstream: int, env: dict[str, str], *args: str) -> tuple[str, str]:
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "proxy", "--upstream", f"127.0.0.1:{upstream}",
         "--listen", str(port), "--debug-core", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        cwd=ROOT,
    )  # fmt: skip
    try:
        wait_port(port, 30.0)
        sock = connect(port)
        for tid in range(10):
            rpc(sock, tid, read_hr(tid, 2))
        rpc(sock, 10, bytes.fromhex("0600640007"))
        sock.sendall(adu(11, 1, bytes.fromhex("2b0e0100")))
        read_adu(sock)
        sock.close()
        time.sleep(0.3)
    finally:
        proc.send_signal(2)
        out, err = proc.communicate(timeout=30)
    return out.decode(), err.decode()


_VARYING = re.compile(
    r'(\d\d:\d\d:\d\d\.\d{6}|"time":[0-9.e+-]+|127\.0\.0\.1:\d+|\(\d+\.\d ms\)|'
    r'"latency_ms":[0-9.]+|"index":\d+|"request_index":\d+)'
)


@pytest.mark.parametrize("as_json", [False, True])
def test_mbmon_proxy_on_the_core_prints_what_the_pure_one_prints(as_json: bool) -> None:
    args = ("--json",) if as_json else ("--plain",)
    with fake() as up:
        core_out, core_err = _run_proxy(up.port, {**ENV}, *args)
        pure_out, pure_err = _run_proxy(up.port, {**ENV, "MBMON_NO_EXTENSIONS": "1"}, *args)
    assert "the compiled core observes the proxy" in core_err
    assert "observed by the compiled core" in core_err
    assert "observed by the compiled core" not in pure_err
    assert _VARYING.sub("_", core_out) == _VARYING.sub("_", pure_out)
    assert core_out.count("\n") >= 25
    if as_json:
        for line in core_out.splitlines():
            json.loads(line)


def test_the_options_the_core_does_not_cover_keep_the_reference(tmp_path: Path) -> None:
    with fake() as up:
        out, err = _run_proxy(up.port, {**ENV}, "--plain", "-w", str(tmp_path / "x.jsonl"))
    assert "declined (-w other than one .mcap log is not covered by the core)" in err
    assert "observed by the compiled core" not in err
    assert out.count("Read Holding Registers") == 20


def test_pipe_scan_reads_whole_records_only() -> None:
    from mbmon.core._reader import pipe_scan

    records = [
        cd.stream(0, "127.0.0.1:1", "127.0.0.1:502"),
        cd.chunk(0, 0, 2.0, b"\x00\x01\x00\x00\x00\x03\x01\x03"),
        cd.event(3.0, 0, "notice", {"message": "x"}),
        cd.chunk(0, 1, 4.0, b""),
    ]
    data = b"".join(records)
    ends = [sum(len(r) for r in records[: i + 1]) for i in range(len(records))]
    for cut in range(len(data) + 1):
        used, chunks, objects = pipe_scan(bytearray(data), cut)
        whole = [e for e in ends if e <= cut]
        assert used == (whole[-1] if whole else 0)
        assert chunks + len(objects) == len(whole)
    assert pipe_scan(bytearray(data), len(data))[1:] == (
        2,
        [(5, ends[0]), (ends[1] + 5, ends[2])],
    )
