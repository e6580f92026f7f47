"""Chunking property: however the upstream's answers are cut into reads, the client
receives exactly the bytes it would get directly (its own transaction ids), in
both TCP modes; per client and shared the pieces go on as they come."""

from __future__ import annotations

import asyncio
import struct
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.proxy.test_proxy_answers import mbap, read_adu, start_upstream
from tests.proxy.test_proxy_e2e import Proxy, connect, recv_exactly


class Cutter:
    """An upstream in a thread of its own that answers the requests of a batch (all
    pipelined) in order, with the bytes of all the answers cut at ``cuts`` and each
    piece written after a short pause (so each is a read of its own)."""

    def __init__(self) -> None:
        self.cuts: list[int] = []
        self.batch = 0
        self.loop = asyncio.new_event_loop()
        ready = threading.Event()
        self.port = 0

        def run() -> None:
            asyncio.set_event_loop(self.loop)
            server, self.port = self.loop.run_until_complete(start_upstream(self.handle))
            ready.set()
            self.loop.run_forever()
            server.close()

        threading.Thread(target=run, daemon=True).start()
        ready.wait(10)

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                reqs = [await read_adu(reader)]
                while len(reqs) < self.batch:
                    reqs.append(await read_adu(reader))
                data = b"".join(answer(r) for r in reqs)
                at = 0
                for cut in [*sorted(c for c in self.cuts if 0 < c < len(data)), len(data)]:
                    if cut > at:
                        writer.write(data[at:cut])
                        await writer.drain()
                        await asyncio.sleep(0.002)
                        at = cut
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)


def answer(req: bytes) -> bytes:
    """Registers from the address on, as many as asked."""
    address, count = struct.unpack(">HH", req[8:12])
    body = bytes([3, 2 * count]) + b"".join(struct.pack(">H", address + i) for i in range(count))
    return mbap((req[0] << 8) | req[1], req[6], body)


@pytest.fixture(scope="module", params=[False, True], ids=["per-client", "share-upstream"])
def setup(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[tuple[Cutter, Proxy]]:
    cutter = Cutter()
    extra = ["--share-upstream"] if request.param else []
    p = Proxy(cutter.port, "--quiet", "--timeout", "5", *extra, tmp=tmp_path_factory.mktemp("c"))
    try:
        yield cutter, p
    finally:
        p.stop()
        cutter.stop()


@settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    reads=st.lists(
        st.tuples(st.integers(0, 0xFFFF), st.integers(0, 1000), st.integers(1, 20)),
        min_size=1,
        max_size=4,
        unique_by=lambda r: r[0],
    ),
    cuts=st.lists(st.integers(1, 200), max_size=12),
)
def test_any_cut_of_the_answers_reaches_the_client_unchanged(
    setup: tuple[Cutter, Proxy], reads: list[tuple[int, int, int]], cuts: list[int]
) -> None:
    cutter, p = setup
    cutter.cuts = cuts
    cutter.batch = len(reads)
    requests = [mbap(tid, 1, struct.pack(">BHH", 3, a, n)) for tid, a, n in reads]
    want = b"".join(answer(r) for r in requests)
    with connect(p.port, timeout=2.0) as sock:  # a wrong cut would leave it waiting
        sock.sendall(b"".join(requests))
        assert recv_exactly(sock, len(want)) == want


def test_the_proxy_made_no_answer_of_its_own(setup: tuple[Cutter, Proxy], tmp_path: Path) -> None:
    """After the property's examples: every answer was the upstream's."""
    cutter, p = setup
    cutter.cuts, cutter.batch = [3, 9], 1
    with connect(p.port) as sock:
        sock.sendall(mbap(1, 1, struct.pack(">BHH", 3, 0, 2)))
        assert recv_exactly(sock, 13) == mbap(1, 1, bytes.fromhex("03 04 00 00 00 01"))
    _out, err = p.stop()
    assert "exceptions made by the proxy 0" in err
    assert "dropped 0" in err
