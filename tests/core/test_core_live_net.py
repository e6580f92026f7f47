"""The core's streaming entry (``sniff`` on the core) keeps what its file entry reads:
noise and MBAP resynchronisation, MBAP length 255, TCP holes (given up by the live
dissector's hole timeout at a tick or a later packet), out-of-order segments, FINs
ahead of data, a connection replaced while open, IPv6 and Modbus/UDP. Each against
``sniff``'s reference wiring (live_diff.py), fed the same packets in the same batches
with the same hub ticks, byte for byte, text and JSON and the summary; and the core
must have kept the run (``covered``). The hand-overs that remain (an idle connection
or UDP pair) carry the new state across: the
reference reassembly the core used, with its holes, and the reference decoder
framing a direction after noise."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
from core_diff import REAL, require_core
from gen import (
    T0,
    adus,
    every_function_pair,
    ipv6_segment,
    noisy_stream,
    perturbed_capture,
    reordered_conversation,
    udp_exchange,
    write_conversation,
    write_frames,
)
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from live_diff import Step, batches, packets_of, reference, with_core

from mbmon.io.pcap import TcpConversation
from mbmon.io.pcap.packets import ACK, PSH
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def assert_same(steps: list[Step], *, covered: bool | None = True, **kw: object) -> str | None:
    """Both paths give the same bytes and summary, text and JSON; ``covered``: whether
    the core must have kept the whole run (``None``: either). Why it handed over."""
    why = None
    for as_json in (False, True):
        ref, ref_summary = reference(steps, as_json=as_json, **kw)  # type: ignore[arg-type]
        got, got_summary, why = with_core(steps, as_json=as_json, **kw)  # type: ignore[arg-type]
        assert got == ref, why
        assert got_summary == ref_summary, why
        if covered is not None:
            assert (why is None) is covered, why
    return why


def _steps(path: Path, sizes: list[int], ticks: list[float] | None = None) -> list[Step]:
    """The packets of ``path`` in batches of ``sizes``, a tick after each batch at its
    last packet's time plus the next of ``ticks`` (none when that is negative)."""
    steps: list[Step] = []
    for i, batch in enumerate(batches(packets_of(path), sizes)):
        steps.append(batch)
        assert isinstance(batch, list)
        if ticks and ticks[i % len(ticks)] >= 0:
            steps.append(batch[-1][0] + ticks[i % len(ticks)])
    return steps


def _ipv6_noisy(path: Path, seed: int) -> Path:
    conv = TcpConversation("[2001:db8::1]:40000", "[2001:db8::2]:502")
    frames = conv.open()
    for n, (client, adu) in enumerate(noisy_stream(seed)):
        ext = ((0, b"\x01\x04\0\0\0\0"),) if n % 3 == 0 else ()
        frames.append(ipv6_segment(conv, client, PSH | ACK, adu, extensions=ext))
    frames += conv.close(True)
    return write_frames(path, [(T0 + i * 0.01, f) for i, f in enumerate(frames)])


# --------------------------------------------------------------------------- noise


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_noise_and_length_255(tmp_path: Path, seed: int) -> None:
    """Noise between and inside ADUs, ADUs of length 255, a capture begun mid-ADU:
    packet by packet, in batches, with ticks that let noise runs settle (the
    decoder's silence) and without."""
    path = write_conversation(tmp_path / "n.pcap", noisy_stream(seed), step=0.3)
    assert_same(_steps(path, [1]))
    assert_same(_steps(path, [3, 1, 7], [0.05, -1.0, 1.5]))


def test_noise_settled_at_a_tick(tmp_path: Path) -> None:
    """A noise run the reference decoder reports after a silence (its tick): the core
    ticks it at the same hub tick."""
    segments = [
        (True, encode_adu(1, 1, encode_read_request(3, 0, 2))),
        (True, b"\x01\x02\x03garbage!"),
        (False, encode_adu(1, 1, encode_read_response(3, [1, 2]))),
        (True, encode_adu(2, 1, encode_read_request(3, 0, 2))),
    ]
    path = write_conversation(tmp_path / "s.pcap", segments, step=3.0, close=None)
    for ticks in ([0.5, 1.5], [2.0], [-1.0]):
        assert_same(_steps(path, [1], ticks))


def test_noise_in_two_directions_settling_at_one_tick(tmp_path: Path) -> None:
    """Noise runs due at one tick in several directions: they settle in the order of
    the pipeline's waiting list (when each direction's decoder began to hold bytes,
    not when it was made), here a server's noise before its client's."""
    a = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    b = TcpConversation("10.0.0.3:40001", "10.0.0.2:502")
    frames = a.open() + b.open()
    frames.append(a.send(True, encode_adu(1, 1, encode_read_request(3, 0, 2))))
    frames.append(b.send(True, encode_adu(1, 1, encode_read_request(3, 0, 2))))
    frames.append(b.send(False, b"\x00\x05\x00\x00\x01\x00\x01"))
    frames.append(a.send(True, b"\x01\x02\x03garbage!"))
    frames.append(a.send(False, encode_adu(1, 1, encode_read_response(3, [1, 2]))))
    frames.append(a.send(False, b"\x00\x00\x00\x00"))
    path = write_frames(tmp_path / "two.pcap", [(T0 + i * 0.01, f) for i, f in enumerate(frames)])
    for sizes in ([100], [1]):
        steps = _steps(path, sizes)
        steps.append(T0 + 5.0)
        assert_same(steps)
        # then idle: the connections expire on the core
        assert_same([*steps, T0 + 400.0, T0 + 1200.0])


# --------------------------------------------------------------------------- holes


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_reordered_lost_and_duplicated_segments(tmp_path: Path, seed: int) -> None:
    """Out-of-order segments, holes that ACKs pass or the end gives up, FINs ahead of
    data, retransmissions, with and without a handshake, closed by FIN, RST or not."""
    close = ("fin", "rst", None, "fin")[seed % 4]
    path = reordered_conversation(tmp_path / "r.pcap", seed, close=close, handshake=seed != 2)
    assert_same(_steps(path, [1]))
    assert_same(_steps(path, [4, 2], [0.001, -1.0]))


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 10_000),
    close=st.sampled_from(["fin", "rst", None]),
    replace=st.booleans(),
    sizes=st.lists(st.integers(1, 9), min_size=1, max_size=4),
    ticks=st.lists(st.sampled_from([-1.0, 0.0, 0.5, 1.5, 2.5]), max_size=4),
)
def test_random_reorderings_batches_and_ticks(
    seed: int, close: str | None, replace: bool, sizes: list[int], ticks: list[float]
) -> None:
    """Any reordering, loss and duplication of a conversation's segments, any batching,
    hub ticks anywhere (holes given up by the hole timeout among them)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = reordered_conversation(Path(tmp) / "r.pcap", seed, close=close, replace=replace)
        why = assert_same(_steps(path, sizes, ticks), covered=None)
        assert why is None or "reset before a FIN" in why, why


def test_a_hole_given_up_by_the_hole_timeout(tmp_path: Path) -> None:
    """A segment held behind a hole: the live dissector gives the hole up 2 s later,
    at a hub tick or at a later packet; the core does the same, then reassembles the
    connection itself again."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = [(T0 + i * 0.01, f) for i, f in enumerate(conv.open())]
    r1 = encode_adu(1, 1, encode_read_request(3, 0, 2))
    r2 = encode_adu(2, 1, encode_read_request(3, 2, 2))
    conv.client_next += len(r1)  # r1 never captured
    frames.append((T0 + 0.1, conv.send(True, r2)))
    frames.append((T0 + 3.0, conv.send(False, encode_adu(2, 1, encode_read_response(3, [5, 6])))))
    frames.append((T0 + 3.1, conv.send(True, encode_adu(3, 1, encode_read_request(3, 4, 1)))))
    frames.append((T0 + 3.2, conv.send(False, encode_adu(3, 1, encode_read_response(3, [7])))))
    path = write_frames(tmp_path / "h.pcap", frames)
    for ticks in ([-1.0], [0.5], [2.5], [0.0, 2.0]):
        assert_same(_steps(path, [1], ticks))
        assert_same(_steps(path, [2, 3], ticks))


def test_idle_connections_with_a_hole_and_noise(tmp_path: Path) -> None:
    """Connections idle for the dissector's 300 s expire on the core as in the
    reference: the one the reference reassembly holds gives its hole up first, the
    noisy one's decoder is flushed; then a packet on the same addresses opens a new
    stream."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    other = TcpConversation("10.0.0.3:40001", "10.0.0.2:502")
    frames = [(T0 + i * 0.01, f) for i, f in enumerate(conv.open() + other.open())]
    r1 = encode_adu(1, 1, encode_read_request(3, 0, 2))
    frames.append((T0 + 0.2, other.send(True, b"\x01\x02\x03garbage!" + r1[:5])))
    conv.client_next += len(r1)
    frames.append((T0 + 0.3, conv.send(True, encode_adu(2, 1, encode_read_request(3, 2, 2)))))
    path = write_frames(tmp_path / "i.pcap", frames)
    steps = _steps(path, [100])
    steps.append(T0 + 0.35)
    steps.append(T0 + 301.0)
    assert_same(steps)
    again = conv.send(True, encode_adu(3, 1, encode_read_request(3, 4, 1)))
    assert_same([*steps, [(T0 + 302.0, 1, again)]])
    assert_same([*steps[:-1], [(T0 + 302.0, 1, again)]])  # expired at that packet


def test_a_connection_replaced_while_open(tmp_path: Path) -> None:
    for seed in (1, 2, 3):
        path = reordered_conversation(tmp_path / f"p{seed}.pcap", seed, replace=True)
        assert_same(_steps(path, [1]))
        assert_same(_steps(path, [5], [2.5]))


# --------------------------------------------------------------------------- IPv6, UDP


def test_ipv6_with_noise_and_extension_headers(tmp_path: Path) -> None:
    path = _ipv6_noisy(tmp_path / "v6.pcap", 7)
    assert_same(_steps(path, [1]))
    assert_same(_steps(path, [5, 2], [0.001, 2.0]))


def test_modbus_udp(tmp_path: Path) -> None:
    """Datagrams, clean and noisy, over IPv4 and IPv6, interleaved with TCP."""
    clean = udp_exchange(tmp_path / "u.pcap", adus(every_function_pair()), step=0.2)
    assert_same(_steps(clean, [1], [0.05]))
    noisy = udp_exchange(tmp_path / "un.pcap", noisy_stream(6))
    assert_same(_steps(noisy, [2, 5]))
    v6 = udp_exchange(
        tmp_path / "u6.pcap", adus(every_function_pair()), client="[::1]:4000", server="[::2]:502"
    )
    assert_same(_steps(v6, [3]))
    tcp = write_conversation(tmp_path / "t.pcap", adus(every_function_pair()))
    mixed = sorted(packets_of(clean) + packets_of(tcp) + packets_of(v6), key=lambda p: p[0])
    assert_same(batches(mixed, [1, 4]))


def test_an_idle_udp_pair(tmp_path: Path) -> None:
    """A UDP pair idle for 300 s ends (its DISCONNECT); its next datagram opens a new
    stream."""
    path = udp_exchange(tmp_path / "u.pcap", adus(every_function_pair()[:2]))
    steps = _steps(path, [10])
    steps.append(T0 + 300.5)
    assert_same(steps)
    later = [(T0 + 301.0 + p[0] - T0, p[1], p[2]) for p in packets_of(path)]
    assert_same([*steps, later])


def test_held_bytes_idle_in_the_sweep_hand_over(tmp_path: Path) -> None:
    """What still hands over: bytes a decoder holds for the pipeline's 600 s sweep;
    the reference then goes on with the core's state (the reference decoder framing a
    noisy direction, its waiting list, the pending request)."""
    conv = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    frames = [(T0 + i * 0.01, f) for i, f in enumerate(conv.open())]
    frames.append((T0 + 0.1, conv.send(True, encode_adu(1, 1, encode_read_request(3, 0, 2)))))
    partial = encode_adu(2, 1, encode_read_request(3, 0, 2))[:5]
    frames.append((T0 + 0.2, conv.send(True, b"\x01\x02\x03garbage!" + partial)))
    for t in (250.0, 500.0):  # pure ACKs keep the connection alive, not its input
        frames.append((T0 + t, conv.segment(True, ACK)))
    path = write_frames(tmp_path / "w.pcap", frames)
    steps = _steps(path, [100])
    steps.append(T0 + 700.0)
    why = assert_same(steps, covered=False)
    assert why is not None and "600 s" in why


# --------------------------------------------------------------------------- real captures


def _real() -> list[Path]:
    if not REAL.is_dir():
        return []
    classic = (b"\xa1\xb2\xc3\xd4", b"\xd4\xc3\xb2\xa1", b"\xa1\xb2\x3c\x4d", b"\x4d\x3c\xb2\xa1")
    return sorted(
        p
        for p in REAL.glob("tcp__*.pcap")
        if p.stat().st_size < 300_000 and p.read_bytes()[:4] in classic
    )


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(which=st.integers(0, 1000), seed=st.integers(0, 1000), size=st.integers(1, 40))
def test_perturbed_public_captures(which: int, seed: int, size: int) -> None:
    """Public captures with records reordered, lost and duplicated (holes, out of
    order, retransmissions on real traffic), in batches with ticks."""
    found = _real()
    if not found:
        pytest.skip(f"no public captures at {REAL}")
    with tempfile.TemporaryDirectory() as tmp:
        path = perturbed_capture(found[which % len(found)], Path(tmp) / "p.pcap", seed)
        assert_same(_steps(path, [size], [0.01, -1.0]), covered=None)


# --------------------------------------------------------------------------- fragments


def test_ip_fragments_on_a_modbus_port(tmp_path: Path) -> None:
    """IP fragments between a conversation's packets: a first fragment is a cut
    packet, later ones are skipped, as the live dissector does."""
    from test_core_net_ip import _fragments

    base = write_conversation(tmp_path / "b.pcap", adus(every_function_pair()[:3]), close=None)
    packets = packets_of(base)
    for n, (_name, frame) in enumerate(_fragments()):
        at = 1 + n % (len(packets) - 1)
        packets.insert(at, (packets[at - 1][0] + 0.0001, 1, frame))
    assert_same(batches(packets, [1]))
    assert_same([*batches(packets, [3, 5]), packets[-1][0] + 2.0])
