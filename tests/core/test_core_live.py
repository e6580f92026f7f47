"""The core's streaming entry (``sniff`` on the core) against ``sniff``'s reference
wiring, fed the same packets in the same batches with the same hub ticks: every
capture in ``captures/`` and ``../shared/captures/real/`` cut into random batches,
generated traffic (handshakes, FIN and RST, connections begun before the capture,
splits at every byte, retransmissions, holes and noise,
timeouts across batch boundaries and at ticks). Byte for byte, text and JSON, and
the summary. Noise, holes, IPv6 and UDP on the core: test_core_live_net.py."""

from __future__ import annotations

import itertools
import tempfile
from pathlib import Path

import pytest
from core_diff import REAL, ROOT, require_core
from gen import (
    T0,
    adus,
    every_function_pair,
    retransmission_and_overlap,
    split_at_every_byte,
    write_conversation,
    write_frames,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from live_diff import Step, batches, packets_of, reference, with_core

from mbmon.io.pcap import TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def _captures() -> list[Path]:
    found = sorted((ROOT / "captures").glob("*.pcap"))
    if REAL.is_dir():
        found += sorted(p for p in REAL.glob("tcp__*.pcap*") if "5view" not in p.name)
    return found


def assert_same(steps: list[Step], *, covered: bool | None = None, **kw: object) -> str | None:
    """Both paths give the same bytes and summary, text and JSON; ``covered``: whether
    the core must have taken the whole run (``None``: either). Why it handed over."""
    why = None
    for as_json in (False, True):
        ref, ref_summary = reference(steps, as_json=as_json, **kw)  # type: ignore[arg-type]
        got, got_summary, why = with_core(steps, as_json=as_json, **kw)  # type: ignore[arg-type]
        assert got == ref, why
        assert got_summary == ref_summary, why
        if covered is not None:
            assert (why is None) is covered, why
    return why


def _steps_of(path: Path, sizes: list[int], ticks: list[float]) -> list[Step]:
    """The packets of ``path`` in batches of ``sizes``, a tick after each batch at its
    last packet's time plus the next of ``ticks`` (none when that is negative)."""
    steps: list[Step] = []
    for i, batch in enumerate(batches(packets_of(path), sizes)):
        steps.append(batch)
        assert isinstance(batch, list)
        if ticks and ticks[i % len(ticks)] >= 0:
            steps.append(batch[-1][0] + ticks[i % len(ticks)])
    return steps


# --------------------------------------------------------------------------- captures


@pytest.mark.parametrize("path", _captures(), ids=lambda p: p.name)
def test_captures_in_batches(path: Path) -> None:
    """Every capture, in batches of 1, 5 and 256 packets with ticks between some."""
    assert_same(_steps_of(path, [1, 5, 256], [0.05, -1.0, 2.0]))


_SMALL = [p for p in _captures() if p.stat().st_size < 200_000]


@settings(max_examples=25, deadline=None)
@given(
    which=st.integers(0, 10_000),
    sizes=st.lists(st.integers(1, 300), min_size=1, max_size=8),
    ticks=st.lists(st.sampled_from([-1.0, 0.0, 0.01, 0.5, 1.0, 3.0, 700.0]), max_size=6),
)
def test_random_batches_and_ticks(which: int, sizes: list[int], ticks: list[float]) -> None:
    """Any batching of a capture, with hub ticks at any of the batches' ends."""
    assert_same(_steps_of(_SMALL[which % len(_SMALL)], sizes, ticks))


# --------------------------------------------------------------------------- generated


def _file_steps(
    path: Path, sizes: list[int] | None = None, ticks: list[float] | None = None
) -> list[Step]:
    return _steps_of(path, sizes or [1], ticks or [])


def test_every_function_code_and_closes(tmp_path: Path) -> None:
    fin = write_conversation(tmp_path / "fin.pcap", adus(every_function_pair()))
    assert_same(_file_steps(fin, [3]), covered=True)
    rst = write_conversation(
        tmp_path / "rst.pcap", adus(every_function_pair()), handshake=False, close="rst"
    )
    assert_same(_file_steps(rst, [2, 7]), covered=True)
    still_open = write_conversation(tmp_path / "open.pcap", adus(every_function_pair()), close=None)
    assert_same(_file_steps(still_open, [4]), covered=True)


def test_half_closed_at_the_end(tmp_path: Path) -> None:
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    frames.append(conv.send(True, encode_adu(1, 1, encode_read_request(3, 0, 2))))
    frames.append(conv.segment(True, 0x11))  # FIN-ACK from the client only
    frames.append(conv.send(False, encode_adu(1, 1, encode_read_response(3, [5, 6]))))
    path = write_frames(tmp_path / "half.pcap", [(T0 + i * 0.01, f) for i, f in enumerate(frames)])
    assert_same(_file_steps(path, [2], [0.5]), covered=True)


def test_splits_at_every_byte(tmp_path: Path) -> None:
    for path in split_at_every_byte(tmp_path):
        assert_same(_file_steps(path, [1, 2]), covered=True)


def test_retransmission_and_overlap(tmp_path: Path) -> None:
    assert_same(_file_steps(retransmission_and_overlap(tmp_path), [1]), covered=True)


def _conversation_with(tmp_path: Path, name: str, trouble: list[bytes]) -> list[Step]:
    """Two connections: the first covered all along, the second with ``trouble``
    (frames) after some covered traffic; then more traffic on the first."""
    a = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    b = TcpConversation("10.0.0.3:40001", "10.0.0.2:502")
    frames = a.open() + b.open()
    for tid in range(1, 4):
        frames.append(a.send(True, encode_adu(tid, 1, encode_read_request(3, tid, 2))))
        frames.append(b.send(True, encode_adu(tid, 2, encode_read_request(3, tid, 1))))
        frames.append(a.send(False, encode_adu(tid, 1, encode_read_response(3, [tid, 7]))))
    frames += [f(b) for f in trouble]  # type: ignore[operator]
    for tid in range(4, 7):
        frames.append(a.send(True, encode_adu(tid, 1, encode_read_request(3, tid, 2))))
        frames.append(a.send(False, encode_adu(tid, 1, encode_read_response(3, [tid, 8]))))
    frames += a.close(True)
    path = write_frames(tmp_path / name, [(T0 + i * 0.2, f) for i, f in enumerate(frames)])
    return _file_steps(path, [3, 1, 4], [0.1, -1.0])


def test_a_hole_stays_on_the_core(tmp_path: Path) -> None:
    """A hole in one connection (a GAP: the peer acknowledges bytes never captured):
    the core resets the direction's decoder as the reference does, and keeps the run."""

    def hole(conv: TcpConversation) -> bytes:
        conv.client_next += 12  # 12 bytes never captured
        return conv.send(True, encode_adu(9, 2, encode_read_request(3, 0, 2)))

    assert_same(_conversation_with(tmp_path, "hole.pcap", [hole]), covered=True)


def test_noise_after_held_bytes_stays_on_the_core(tmp_path: Path) -> None:
    """Noise after a partial ADU held in the core: the held bytes go to the reference's
    decoder (inside the core), which reports them as the reference would have."""
    partial = encode_adu(9, 2, encode_read_request(3, 0, 2))[:9]
    steps = _conversation_with(
        tmp_path,
        "noise.pcap",
        [lambda c: c.send(True, partial), lambda c: c.send(True, b"\x01\x02garbage!")],
    )
    assert_same(steps, covered=True)


def test_out_of_order_stays_on_the_core(tmp_path: Path) -> None:
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = conv.open()
    r1 = encode_adu(1, 1, encode_read_request(3, 0, 2))
    r2 = encode_adu(2, 1, encode_read_request(3, 2, 2))
    seq = conv.client_next
    frames.append(conv.segment(True, 0x18, r2, seq=seq + len(r1), advance=False))
    frames.append(conv.segment(True, 0x18, r1, seq=seq, advance=False))
    conv.client_next = (seq + len(r1) + len(r2)) & 0xFFFFFFFF
    frames.append(conv.send(False, encode_adu(1, 1, encode_read_response(3, [1, 2]))))
    frames += conv.close(True)
    path = write_frames(tmp_path / "ooo.pcap", [(T0 + i * 0.01, f) for i, f in enumerate(frames)])
    assert_same(_file_steps(path, [1, 2]), covered=True)


def test_timeouts_across_batches_and_ticks(tmp_path: Path) -> None:
    """Unanswered requests time out at ticks between batches, at the next packet's
    pipeline tick, or at the end; reused ids time the old request out."""
    req = encode_adu(1, 1, encode_read_request(3, 0, 2))
    segments = [(True, req), (True, req), (True, encode_adu(2, 1, encode_read_request(4, 0, 1)))]
    segments += [(True, encode_adu(3, 9, encode_read_request(1, 0, 8)))]
    segments += [(False, encode_adu(3, 9, b"\x01\x01\x05"))]
    times = [T0, T0 + 0.001, T0 + 0.002] + [T0 + 0.003 + 0.7 * i for i in range(9)]
    path = write_conversation(tmp_path / "to.pcap", segments, times=times)
    for sizes in ([1], [2, 3], [50]):
        for ticks in ([0.0], [0.4, 1.2], [5.0], []):
            assert_same(_file_steps(path, sizes, ticks), covered=True)
            assert_same(_file_steps(path, sizes, ticks), covered=True, timeout=0.1)


def test_an_idle_connection_expires_on_the_core(tmp_path: Path) -> None:
    """A connection without packets for the dissector's idle timeout expires (a
    DISCONNECT ``how="idle"``) at the tick at that time, on the core."""
    path = write_conversation(tmp_path / "idle.pcap", adus(every_function_pair()[:3]), close=None)
    steps = _file_steps(path, [100])
    last = steps[-1]
    assert isinstance(last, list)
    steps.append(last[-1][0] + 301.0)
    assert_same(steps, covered=True)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    cuts=st.lists(st.integers(0, 10_000), max_size=30),
    sizes=st.lists(st.integers(1, 6), min_size=1, max_size=5),
    gap=st.sampled_from([0.0005, 0.3, 1.5]),
)
def test_random_segmentations_and_batches(cuts: list[int], sizes: list[int], gap: float) -> None:
    stream = adus(every_function_pair())
    client = b"".join(a for c, a in stream if c)
    server = [(False, a) for c, a in stream if not c]
    points = sorted({c % (len(client) + 1) for c in cuts} | {0, len(client)})
    pieces = [(True, client[a:b]) for a, b in itertools.pairwise(points) if b > a]
    segments: list[tuple[bool, bytes]] = []
    while pieces or server:
        if pieces:
            segments.append(pieces.pop(0))
        if server:
            segments.append(server.pop(0))
    with tempfile.TemporaryDirectory() as tmp:
        path = write_conversation(Path(tmp) / "r.pcap", segments, step=gap)
        assert_same(_file_steps(path, sizes, [gap / 2]), covered=True)
