"""The least any Python observer can spend on what mbmon's proxy forwards.

    python bench/proxy_floor.py STAGE --upstream HOST:PORT    # serve until Ctrl-C

Why this exists: the target asks ``mbmon proxy`` for at least 0.8x the bare
forwarder's throughput at 8 clients, and an added p50 at most 1.5x the bare
forwarder's, while it observes (and logs) every request. The forwarding and the
observing share the machine's cores with the clients and the upstream, so what
the targets allow the observation to cost is a CPU budget per request. This
script measures how little *any* Python observer can spend, on mbmon's own
forwarding, so that the targets can be judged against that floor rather than
against a guess (``bench/python_floor.py`` does the same for ``read``). It is
not mbmon and mbmon never imports it.

It runs mbmon's forwarding process as ``mbmon proxy`` does
(:class:`~mbmon.proxy.remote.ProxyProcess`: the engine in a child process,
its copies through the pipe, rebuilt into chunks by the parent's reader thread),
with a floor observer in place of the hub. The floor observer does its work in
the reader thread itself (no queue, no second thread: its best case), in one of
three stages:

1. ``copies``: the chunks rebuilt and counted, nothing else. What the copy
   alone costs: the child's encoding, the pipe, the parent's reads.
2. ``decode``: plus MBAP framing (a chunk that is exactly one ADU taken whole,
   else a buffer per connection direction), mbmon's ``decode_pdu`` and
   pairing by (connection, transaction id, unit) with latency. No records.
3. ``log``: plus one JSON line per ADU (``orjson``: time, connection,
   direction, ids, function code, address, count, values, latency), written to
   a file in blocks: less than any log mbmon could write (no schema, no
   chunking, no compression, no notes, no index).

What the floor leaves out, and mbmon cannot: records, exceptions and
malformed PDUs told apart, timeouts, connect/disconnect and proxy events,
notes and labels, counters and the summary, the live monitor, a log that
Foxglove opens. So it is a lower bound of what observing costs, not an
estimate of it.

``--inline`` runs the floor observer in the forwarding process itself instead:
mbmon's engine on the same event loop (uvloop), its batches handed to the floor
observer every handover in the loop's thread. No copy and no pipe, but the
observer's work and the forwarding share one thread: the other way a Python
proxy can observe.

``bench/proxy_latency.py --floor-observers`` runs the three stages as targets,
next to the bare forwarder and ``mbmon proxy`` in the same minutes. Like
``mbmon proxy``, it writes ``listening on 127.0.0.1:PORT`` to stderr once it
listens, and its counters (the proxy's own summary) when Ctrl-C stops it.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any, BinaryIO

import orjson

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from mbmon.model import Chunk, Direction, Stream, Transport
from mbmon.protocol.pdu import decode_pdu
from mbmon.proxy.config import ProxyConfig, ProxyStats
from mbmon.proxy.engine import ProxyEngine
from mbmon.proxy.observer import Observer
from mbmon.proxy.remote import ProxyProcess, run_loop

STAGES = ("copies", "decode", "log")


class FloorHub:
    """What :class:`~mbmon.proxy.remote.ProxyProcess` needs of a hub (``new_stream``,
    ``submit``, ``seen``), doing the floor's work at once in the caller's thread."""

    def __init__(self, stage: str, log: BinaryIO | None = None) -> None:
        self.stage = STAGES.index(stage) + 1
        self.log = log
        self.seen = 0
        self.adus = 0
        self.pairs = 0
        self._ids = 0
        self._held: dict[tuple[int, Direction], bytes] = {}
        self._pending: dict[tuple[int, int, int], tuple[float, Any]] = {}

    def new_stream(self, transport: Transport, client: str, server: str) -> Stream:
        stream = Stream(self._ids, transport, client, server)
        self._ids += 1
        return stream

    def submit(self, make: Any) -> None:
        items = make()
        if self.stage > 1:
            self._observe(items)
        self.seen += len(items)

    def _observe(self, items: list[Any]) -> None:
        """Frame, decode and pair every chunk of ``items`` (and log each ADU at stage 3)."""
        held = self._held
        pending = self._pending
        log = self.stage > 2
        lines: list[bytes] = []
        dumps = orjson.dumps
        c2s = Direction.C2S
        for item in items:
            if type(item) is not Chunk:
                continue
            data = item.data
            sid = item.stream.id
            key = (sid, item.direction)
            if key in held:
                data = held.pop(key) + data
            ts = item.ts
            response = item.direction is not c2s
            pos, n = 0, len(data)
            while n - pos >= 7:
                end = pos + 6 + ((data[pos + 4] << 8) | data[pos + 5])
                if end > n:
                    break
                tid = (data[pos] << 8) | data[pos + 1]
                unit = data[pos + 6]
                pdu = decode_pdu(data[pos + 7 : end], response)
                self.adus += 1
                latency = None
                if response:
                    asked = pending.pop((sid, tid, unit), None)
                    if asked is not None:
                        latency = ts - asked[0]
                        self.pairs += 1
                else:
                    pending[(sid, tid, unit)] = (ts, pdu)
                if log:
                    lines.append(
                        dumps(
                            {
                                "ts": ts,
                                "stream": sid,
                                "dir": "s2c" if response else "c2s",
                                "tid": tid,
                                "unit": unit,
                                "fc": pdu.fc,
                                "address": pdu.address,
                                "count": pdu.count,
                                "values": pdu.values,
                                "latency": latency,
                            }
                        )
                    )
                pos = end
            if pos < n:
                held[key] = data[pos:]
        if lines and self.log is not None:
            lines.append(b"")
            self.log.write(b"\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stage", choices=STAGES, help="how much the floor observer does")
    parser.add_argument("--upstream", required=True, metavar="HOST:PORT")
    parser.add_argument("--listen", default="127.0.0.1:0", metavar="ADDR:PORT")
    parser.add_argument("-w", dest="log", metavar="FILE", help="stage 'log': the JSON lines' file")
    parser.add_argument(
        "--inline",
        action="store_true",
        help="observe in the forwarding process's own loop (no copy, no pipe)",
    )
    args = parser.parse_args()
    up_host, _, up_port = args.upstream.rpartition(":")
    host, _, port = args.listen.rpartition(":")
    config = ProxyConfig(
        upstream_host=up_host, upstream_port=int(up_port), listen_host=host, listen_port=int(port)
    )
    log = open(args.log or os.devnull, "wb", buffering=1 << 20) if args.stage == "log" else None
    hub = FloorHub(args.stage, log)
    if args.inline:
        stats = inline(config, hub)
    else:
        stats = through_the_pipe(config, hub)
    if log is not None:
        log.close()
    print(stats.summary(), file=sys.stderr)
    print(f"floor {args.stage}: ADUs framed {hub.adus}, pairs {hub.pairs}", file=sys.stderr)


def through_the_pipe(config: ProxyConfig, hub: FloorHub) -> ProxyStats:
    """Forward as ``mbmon proxy`` does, in a child process; observe its copies here."""
    ended = threading.Event()
    proc = ProxyProcess(config, hub, on_exit=ended.set)
    address = proc.start()
    print(f"listening on {address[0]}:{address[1]}", file=sys.stderr, flush=True)
    signal.signal(signal.SIGINT, lambda *_: proc.stop())
    signal.signal(signal.SIGTERM, lambda *_: proc.stop())
    while not ended.wait(0.5):
        pass
    proc.join(10)
    return proc.engine.stats


def inline(config: ProxyConfig, hub: FloorHub) -> ProxyStats:
    """Forward with mbmon's engine here, and observe in its loop every handover."""
    observer = Observer(lambda item: hub.submit(lambda: [item]), hub.new_stream, meter=hub)
    engine = ProxyEngine(config, observer, submit=hub.submit)

    async def serve() -> None:
        address = await engine.start()
        print(f"listening on {address[0]}:{address[1]}", file=sys.stderr, flush=True)
        loop = asyncio.get_running_loop()
        loop.add_signal_handler(signal.SIGINT, engine.request_stop)
        loop.add_signal_handler(signal.SIGTERM, engine.request_stop)
        await engine.serve()
        observer.flush()  # the last batch, its handover not yet due

    run_loop(serve())
    return engine.stats


if __name__ == "__main__":
    main()
