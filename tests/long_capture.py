"""A Modbus/TCP capture that takes mbmon seconds to read: the input of the tests that
stop a running ``read`` (signals, kills) and must find it still reading."""

from __future__ import annotations

from pathlib import Path

from mbmon.io.pcap import PcapWriter, TcpConversation

_REQUEST = bytes.fromhex("0000000601030064000A")  # after the tid: read R100..R109
_ANSWER = bytes.fromhex("00000017010314") + bytes(20)


def write_long_capture(path: Path, segments: int) -> Path:
    """``segments`` request segments and their answers, 25 pipelined ADUs each, 1 ms
    apart, on one connection from its handshake."""
    conv = TcpConversation("10.0.0.2:40000", "10.0.0.1:502")
    ts = 1_700_000_000.0
    with PcapWriter(path) as w:
        for frame in conv.open():
            w.write(ts, frame)
        tid = 0
        for _ in range(segments):
            reqs, resps = [], []
            for _ in range(25):
                tid = (tid + 1) & 0xFFFF
                reqs.append(tid.to_bytes(2, "big") + _REQUEST)
                resps.append(tid.to_bytes(2, "big") + _ANSWER)
            ts += 0.001
            w.write(ts, conv.send(True, b"".join(reqs)))
            ts += 0.001
            w.write(ts, conv.send(False, b"".join(resps)))
    return path
