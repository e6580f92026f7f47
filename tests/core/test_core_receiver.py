"""The core's capture reader (``_Receiver``: ``recvmmsg``, many packets per system
call) against the one-at-a-time reading it replaces, on a real socket pair: the same
bytes in the same order, the kernel's SO_TIMESTAMPNS times (``sec + nsec * 1e-9``, as
scapy computes them), the room asked for respected, nothing waiting: 0. On a live
interface ``test_core_live_lo.py`` holds sniff on the core (this reader) equal to
sniff forced pure (scapy's reader)."""

from __future__ import annotations

import socket
import struct
import time

from core_diff import require_core

from mbmon import core

SO_TIMESTAMPNS = 35


def _pair() -> tuple[socket.socket, socket.socket]:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    b.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    b.setblocking(False)
    return a, b


def test_receiver_reads_what_recvmsg_reads() -> None:
    require_core()
    payloads = [bytes([i]) * (1 + i * 37 % 1500) for i in range(150)]
    a, b = _pair()
    a2, b2 = _pair()
    got: list[tuple[float, int, bytes]] = []
    want: list[tuple[float, int, bytes]] = []
    with a, b, a2, b2:
        rx = core._reader._Receiver(b.fileno(), 1, False)
        assert rx.read(got, 0) == 0
        before = time.time()
        for at in range(0, len(payloads), 8):  # a datagram socket queues a few only
            group = payloads[at : at + 8]
            for p in group:
                a.send(p)
                a2.send(p)
            room = 1 + at % 9  # in reads of 1 to 9
            while len(got) < at + len(group):
                n = rx.read(got, room)
                assert 0 < n <= room
            assert rx.read(got, 10) == 0  # nothing waiting
            # one at a time, as scapy's _recv_raw reads and times them
            for _ in group:
                data, anc, _flags, _addr = b2.recvmsg(65535, socket.CMSG_LEN(4096))
                ts = None
                for level, kind, cdata in anc:
                    if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                        sec, nsec = struct.unpack("ll", cdata)
                        ts = sec + nsec * 1e-9
                assert ts is not None
                want.append((ts, 1, data))
        after = time.time()
    assert [g[2] for g in got] == [w[2] for w in want] == payloads
    assert all(g[1] == 1 for g in got)
    for ts, _, _ in got:
        assert before - 1 <= ts <= after + 1
        assert ts == float(repr(ts))
