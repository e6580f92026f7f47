"""The core against the reference pipeline on TCP as a capture misses and reorders it:
out-of-order segments, holes (an ACK beyond unseen bytes, a FIN ahead of data, holes
given up at a reset, the end or the hold limit), payload after a connection or a
direction ended, a connection replaced on the same addresses while open; byte for
byte, text and JSON (and the MCAP log); random reorderings (hypothesis)."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import pytest
from core_diff import REAL, ROOT, assert_same, require_core, with_core
from gen import (
    T0,
    adus,
    every_function_pair,
    perturbed_capture,
    reordered_conversation,
    write_frames,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap_diff import assert_same_log

from mbmon.io.pcap import TcpConversation
from mbmon.io.pcap.packets import ACK, FIN, PSH, RST, SYN
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def _req(tid: int) -> bytes:
    return encode_adu(tid, 1, encode_read_request(3, tid, 2))


def _resp(tid: int) -> bytes:
    return encode_adu(tid, 1, encode_read_response(3, [tid, 9]))


def _write(tmp: Path, name: str, frames: list[bytes], step: float = 0.01) -> Path:
    return write_frames(tmp / name, [(T0 + i * step, f) for i, f in enumerate(frames)])


def _events(path: Path) -> list[dict]:
    out, _, why = with_core(path, as_json=True)
    assert why is None
    return [r for r in map(json.loads, out.splitlines()) if r["kind"] == "event"]


def test_out_of_order_segments(tmp_path: Path) -> None:
    """A segment ahead of a hole is held and delivered (with its own time) once the
    hole fills; the connection is the core's again after it."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    first = conv.send(True, _req(1))
    second = conv.send(True, _req(2)[:5])
    third = conv.send(True, _req(2)[5:] + _req(3))
    frames += [third, second, first]  # backwards
    frames += [conv.send(False, _resp(1) + _resp(2)), conv.send(False, _resp(3))]
    frames += [conv.send(True, _req(4)), conv.send(False, _resp(4))]
    frames += conv.close(True)
    path = _write(tmp_path, "ooo.pcap", frames)
    assert_same(path, covered=True)
    assert not any(e["event"] == "gap" for e in _events(path))


def test_an_ack_beyond_unseen_bytes(tmp_path: Path) -> None:
    """A request the capture missed, acknowledged by the server's answer: a GAP
    (acked-unseen); an ADU half held before it is noise ("discarded after gap")."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    frames.append(conv.send(True, _req(1)))
    frames.append(conv.send(False, _resp(1)))
    frames.append(conv.send(True, _req(2)[:7]))
    conv.send(True, _req(2)[7:] + _req(3))  # lost
    frames.append(conv.send(False, _resp(2)))
    frames.append(conv.send(True, _req(4)))
    conv.send(False, _resp(4))  # lost: the client's FIN acknowledges it
    frames += conv.close(True)
    path = _write(tmp_path, "acked.pcap", frames)
    assert_same(path, covered=True)
    gaps = [e for e in _events(path) if e["event"] == "gap"]
    assert [g["info"]["reason"] for g in gaps] == ["acked-unseen", "acked-unseen"]


def test_a_fin_ahead_of_data(tmp_path: Path) -> None:
    """A FIN seen before the bytes in front of it: the end waits for them (the
    DISCONNECT after the last answer); never filled, the end gives the hole up."""
    for fill in (True, False):
        conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
        frames = conv.open()
        frames.append(conv.send(True, _req(1)))
        answer = conv.send(False, _resp(1))
        fin = conv.segment(False, FIN | ACK)
        frames.append(fin)
        if fill:
            frames.append(answer)
            frames.append(conv.segment(True, FIN | ACK))
            frames.append(conv.segment(False, ACK))
        path = _write(tmp_path, f"fin{fill}.pcap", frames)
        assert_same(path, covered=True)
        kinds = [(e["event"], e["info"].get("reason")) for e in _events(path)]
        assert ("gap", "end-of-capture") in kinds or fill


def test_holes_given_up_at_a_reset(tmp_path: Path) -> None:
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    frames.append(conv.send(True, _req(1)))
    conv.send(True, _req(2))  # lost
    frames.append(conv.send(True, _req(3)))  # held behind the hole
    frames.append(conv.segment(False, RST | ACK, ack=conv.client_next - 100, advance=False))
    path = _write(tmp_path, "rst.pcap", frames)
    assert_same(path, covered=True)
    events = [(e["event"], e["info"].get("reason")) for e in _events(path)]
    assert events[:3] == [("connect", None), ("gap", "reset"), ("disconnect", None)]


def test_payload_after_the_end(tmp_path: Path) -> None:
    """Payload after a reset (a straggler: dropped), after a direction's FIN (dropped),
    and far from the old numbers (a new connection whose handshake was missed)."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    frames.append(conv.send(True, _req(1)))
    frames.append(conv.segment(True, FIN | ACK))
    frames.append(conv.segment(True, PSH | ACK, _req(9)))  # after its FIN
    frames.append(conv.send(False, _resp(1)))
    frames.append(conv.reset(False))
    frames.append(conv.send(False, _resp(1)))  # straggler after the reset
    conv.client_next += 1 << 24  # a new connection on the same addresses
    frames.append(conv.send(True, _req(5)))
    frames.append(conv.send(False, _resp(5)))
    path = _write(tmp_path, "after.pcap", frames)
    assert_same(path, covered=True)


def test_a_connection_replaced_while_open(tmp_path: Path) -> None:
    """A SYN with another initial number on open addresses: the old connection's holes
    are given up ("replaced") and it is forgotten (no DISCONNECT); its requests time
    out at the end; held bytes of its stream are noise at the end."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    frames.append(conv.send(True, _req(1)))
    frames.append(conv.send(True, _req(2)[:4]))
    conv.send(True, _req(3))  # lost
    frames.append(conv.send(True, _req(4)))  # held behind the hole
    new = TcpConversation("10.0.0.1:40000", "10.0.0.2:502", client_isn=777, server_isn=99)
    frames += new.open()
    frames += [new.send(True, _req(1)), new.send(False, _resp(1))]
    frames += new.close(False)
    path = _write(tmp_path, "replaced.pcap", frames)
    assert_same(path, covered=True)
    kinds = [(e["event"], e["info"].get("reason")) for e in _events(path)]
    assert ("gap", "replaced") in kinds
    assert_same_log(path, tmp_path, covered=True)


def test_the_hold_limit(tmp_path: Path) -> None:
    """More than 1 MiB held behind a hole: the hole is given up (buffer-limit)."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    conv.send(True, _req(1))  # lost
    big = encode_adu(2, 1, b"\x10\x00\x00\x00\x7b\xf6" + bytes(246))
    frames += [conv.send(True, big * 180) for _ in range(25)]  # 1.15 MB held
    path = _write(tmp_path, "limit.pcap", frames, step=0.0001)
    assert_same(path, covered=True)
    assert ("gap", "buffer-limit") in [(e["event"], e["info"].get("reason")) for e in _events(path)]


def test_holes_with_a_log(tmp_path: Path) -> None:
    path = reordered_conversation(tmp_path / "log.pcap", seed=11)
    assert_same_log(path, tmp_path, covered=True)


def test_real_captures_with_holes() -> None:
    names = ["tcp__zeek__fuzz-72.pcap", "tcp__zeek__fuzz-1011.pcap", "tcp__zeek__modbusBig.pcap"]
    paths = [REAL / name for name in names if (REAL / name).is_file()]
    if not paths:
        pytest.skip(f"{REAL} absent (../shared/captures/real)")
    for path in paths:
        assert_same(path, covered=True)


@pytest.mark.parametrize("seed", range(6))
def test_reordered_conversations(tmp_path: Path, seed: int) -> None:
    for close, replace in (("fin", False), ("rst", True), (None, False)):
        path = reordered_conversation(
            tmp_path / f"r{close}.pcap", seed, close=close, replace=replace
        )
        assert_same(path, covered=True)


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    seed=st.integers(0, 2**32 - 1),
    close=st.sampled_from(["fin", "rst", None]),
    handshake=st.booleans(),
    replace=st.booleans(),
)
def test_random_reorderings(seed: int, close: str | None, handshake: bool, replace: bool) -> None:
    """Any reordering, loss and duplication of a conversation's segments gives the
    same lines through both paths."""
    with tempfile.TemporaryDirectory() as tmp:
        path = reordered_conversation(
            Path(tmp) / "r.pcap", seed, close=close, handshake=handshake, replace=replace
        )
        assert_same(path, covered=True)


def test_segments_of_both_directions_held(tmp_path: Path) -> None:
    """Both directions out of order at once; a SYN retransmitted mid-way."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    syn, syn_ack, ack = conv.open()
    stream = adus(every_function_pair()[:6])
    sent = [conv.send(c, a) for c, a in stream]
    frames = [syn, syn_ack, ack, sent[1], sent[0], syn, sent[3], sent[2], *sent[4:]]
    frames.append(conv.segment(True, SYN, seq=conv.client_isn, advance=False))
    path = _write(tmp_path, "both.pcap", frames)
    assert_same(path, covered=True)


def test_noise_and_holes_under_a_profile(tmp_path: Path) -> None:
    """The same with ``--profile hrss``: frames the reference decoder and reassembly
    give are annotated (or noted by the core) as the reference annotates them."""
    from test_core_profile import assert_same as assert_same_profiled

    for seed in (1, 2):
        path = reordered_conversation(tmp_path / f"p{seed}.pcap", seed, replace=True)
        assert_same_profiled(path, ["hrss"])
        assert_same_profiled(path, ["unit:1=hrss"], timeout=0.05)


@pytest.mark.parametrize("name", ["demo.pcap", "hrss_ptp.pcap", "sim_functions.pcap"])
def test_perturbed_captures(tmp_path: Path, name: str) -> None:
    """The project's captures with records reordered, lost and duplicated; hrss_ptp's
    under its profile too."""
    from test_core_profile import assert_same as assert_same_profiled

    for seed in range(3):
        path = perturbed_capture(ROOT / "captures" / name, tmp_path / f"{seed}{name}", seed)
        assert_same(path, covered=True)
        if name == "hrss_ptp.pcap":
            assert_same_profiled(path, ["hrss"])


def test_perturbed_real_captures(tmp_path: Path) -> None:
    paths = sorted(p for p in REAL.glob("tcp__*.pcap")) if REAL.is_dir() else []
    if not paths:
        pytest.skip(f"{REAL} absent (../shared/captures/real)")
    for path in paths:
        assert_same(perturbed_capture(path, tmp_path / path.name, seed=len(path.name)))
