"""Log format 4 on the compiled core: the chunks it leaves out and the markers it writes
are the pure layout's, byte for byte, also where the frame after a chunk takes the
layout's slow path (every function code, Modbus/UDP: the core hands the chunk back to
the layout) and across block boundaries (about 1 MiB of messages each) with kept and
left-out chunks mixed."""

from __future__ import annotations

from pathlib import Path

import pytest
from core_diff import require_core
from format4 import left_out
from gen import adus, every_function_pair, udp_exchange, write_conversation
from mcap_diff import assert_same_log, log_contents

from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response


@pytest.fixture(autouse=True)
def _core() -> None:
    require_core()


def _left_out(log: Path) -> tuple[int, int]:
    """(chunks left out, frames messages) of a log."""
    messages = [(t, lt, d) for t, _seq, lt, _pub, d in log_contents(log)["messages"]]
    return left_out(messages), sum(t == "/modbus/frames" for t, _, _ in messages)


def test_slow_path_frames_take_their_chunk_back(tmp_path: Path) -> None:
    """Every function code, one ADU a segment: the frames the core formats itself and
    those it hands to the layout both leave their chunk out (and the same bytes)."""
    pairs = every_function_pair()
    path = write_conversation(tmp_path / "fc.pcap", adus(pairs))
    assert assert_same_log(path, tmp_path, covered=True) is None
    marked, frames = _left_out(tmp_path / "core0.mcap")
    assert marked == frames == 2 * len(pairs)


def test_modbus_udp_datagrams(tmp_path: Path) -> None:
    datagrams = []
    for tid in range(1, 40):
        datagrams += [
            (True, encode_adu(tid, 1, encode_read_request(3, tid, 2))),
            (False, encode_adu(tid, 1, encode_read_response(3, [tid, 7]))),
        ]
    datagrams.append((True, encode_adu(99, 1, encode_read_request(3, 0, 1)) * 2))  # two ADUs
    path = udp_exchange(tmp_path / "udp.pcap", datagrams)
    why = assert_same_log(path, tmp_path)
    if why is not None:
        pytest.skip(f"the core declines Modbus/UDP here: {why}")
    marked, frames = _left_out(tmp_path / "core0.mcap")
    assert marked == frames - 2 == len(datagrams) - 1


def test_blocks_of_a_mixed_capture(tmp_path: Path) -> None:
    """About 5 MB of messages (five blocks): one ADU a segment, every 5th request split
    in two, every 7th pair of requests in one segment, every 13th exchange with a
    function the layout formats (0x2B): kept and left-out chunks on both sides of every
    block boundary."""
    segments: list[tuple[bool, bytes]] = []
    tid = 0
    for n in range(4500):
        tid = tid % 65535 + 1
        req = encode_adu(tid, 1, encode_read_request(3, n % 1000, 4))
        if n % 13 == 0:
            req = encode_adu(tid, 1, bytes.fromhex("2B0E0100"))
            resp = encode_adu(tid, 1, bytes.fromhex("2B0E01010000010003616263"))
        else:
            resp = encode_adu(tid, 1, encode_read_response(3, [n, n + 1, 7, 65535]))
        if n % 5 == 0:
            segments += [(True, req[:3]), (True, req[3:])]
        elif n % 7 == 0 and segments:
            tid = tid % 65535 + 1
            second = encode_adu(tid, 1, encode_read_request(3, 1, 1))
            segments.append((True, req + second))
            segments.append((False, resp))
            resp = encode_adu(tid, 1, encode_read_response(3, [1]))
        else:
            segments.append((True, req))
        segments.append((False, resp))
    path = write_conversation(tmp_path / "mixed.pcap", segments)
    assert assert_same_log(path, tmp_path, covered=True) is None
    marked, frames = _left_out(tmp_path / "core0.mcap")
    assert (tmp_path / "core0.mcap").stat().st_size > 0
    assert frames > marked > frames // 2
