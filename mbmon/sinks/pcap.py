"""Pcap sink (``-w FILE.pcap`` and ``mbmon export LOG.mcap -o FILE.pcap``).

Owns how captured bytes are re-wrapped so Wireshark decodes them: every TCP
stream (Modbus/TCP, RTU over TCP) becomes one Ethernet/IP/TCP conversation with
consistent sequence and acknowledgement numbers, its original endpoints and
capture times (a three-way handshake when the connect was seen, FIN or RST on
disconnect, a lone FIN for a connection only half closed); UDP chunks become
UDP datagrams; bytes of an RS485 bus become records of link type 147 (USER0),
one per captured chunk.

A classic pcap file holds one link type. The first chunk decides the file's
type; if the session also has the other kind of stream, those packets go to a
companion file next to it: ``NAME.rtu.pcap`` (link type 147) or
``NAME.tcp.pcap`` (Ethernet).
"""

from __future__ import annotations

from pathlib import Path

from mbmon.model import Chunk, Direction, Event, EventKind, Stream, Transport
from mbmon.sinks.base import SinkBase, SinkContext
from mbmon.sources.pcapwrite import (
    ACK,
    FIN,
    LINKTYPE_ETHERNET,
    LINKTYPE_USER0,
    PcapWriter,
    TcpConversation,
    parse_endpoint,
    udp_frame,
)

_MAX_SEGMENT = 32768  # larger chunks are cut into several segments (IPv4 length limit)
_IP, _RTU = "ip", "rtu"


class PcapSink(SinkBase):
    """Raw chunks and connect/disconnect events out as a pcap Wireshark can dissect."""

    def __init__(self, path: str | Path, ctx: SinkContext | None = None) -> None:
        self.path = Path(path)
        self.ctx = ctx
        self._writers: dict[str, PcapWriter] = {}
        self._primary: str | None = None
        self._tcp: dict[int, TcpConversation] = {}
        self._skipped = 0
        self._closed = False
        # fail early (bad directory, no permission) rather than at the first chunk
        self.path.open("ab").close()

    @property
    def companion(self) -> Path | None:
        """The second file, when the session mixed RTU buses and IP streams."""
        for kind in self._writers:
            if kind != self._primary:
                return self._companion_path(kind)
        return None

    @property
    def skipped(self) -> int:
        """Chunks that could not be wrapped (endpoints that are not IP:PORT)."""
        return self._skipped

    def _companion_path(self, kind: str) -> Path:
        return self.path.with_name(f"{self.path.stem}.{'rtu' if kind == _RTU else 'tcp'}.pcap")

    def _writer(self, kind: str) -> PcapWriter:
        writer = self._writers.get(kind)
        if writer is None:
            if self._primary is None:
                self._primary = kind
                target = self.path
            else:
                target = self._companion_path(kind)
            linktype = LINKTYPE_USER0 if kind == _RTU else LINKTYPE_ETHERNET
            writer = PcapWriter(target, linktype)
            self._writers[kind] = writer
        return writer

    def _conversation(self, stream: Stream) -> TcpConversation | None:
        conv = self._tcp.get(stream.id)
        if conv is None:
            try:
                conv = TcpConversation(
                    stream.client,
                    stream.server,
                    client_isn=(1000 + stream.id * 7919) & 0xFFFFFFFF,
                    server_isn=(500000 + stream.id * 104729) & 0xFFFFFFFF,
                )
            except ValueError:
                return None
            self._tcp[stream.id] = conv
        return conv

    # ------------------------------------------------------------------ sink API

    def on_chunk(self, chunk: Chunk) -> None:
        stream = chunk.stream
        transport = stream.transport
        ts = chunk.ts
        if transport is Transport.RTU:
            self._writer(_RTU).write(ts, chunk.data)
            return
        from_client = chunk.direction is not Direction.S2C
        if transport is Transport.TCP or transport is Transport.RTU_OVER_TCP:
            conv = self._conversation(stream)
            if conv is None:
                self._skipped += 1
                return
            writer = self._writer(_IP)
            data = chunk.data
            for start in range(0, max(len(data), 1), _MAX_SEGMENT):
                writer.write(ts, conv.send(from_client, data[start : start + _MAX_SEGMENT]))
            return
        try:
            src_ip, src_port = parse_endpoint(stream.src(chunk.direction))
            dst_ip, dst_port = parse_endpoint(stream.dst(chunk.direction))
            frame = udp_frame(LINKTYPE_ETHERNET, src_ip, dst_ip, src_port, dst_port, chunk.data)
        except ValueError:
            self._skipped += 1
            return
        self._writer(_IP).write(ts, frame)

    def on_event(self, event: Event) -> None:
        """Connect: a three-way handshake; disconnect: FIN/FIN/ACK or an RST."""
        stream = event.stream
        if stream is None or stream.transport not in (Transport.TCP, Transport.RTU_OVER_TCP):
            return
        if event.kind is EventKind.CONNECT:
            self._tcp.pop(stream.id, None)
            conv = self._conversation(stream)
            if conv is None:
                return
            writer = self._writer(_IP)
            for frame in conv.open():
                writer.write(event.ts, frame)
        elif event.kind is EventKind.DISCONNECT:
            conv = self._tcp.get(stream.id)
            if conv is None:
                return
            by_client = event.info.get("by", "client") != "server"
            writer = self._writer(_IP)
            if event.info.get("how") == "rst":
                writer.write(event.ts, conv.reset(by_client))
            elif event.info.get("half_closed"):
                writer.write(event.ts, conv.segment(by_client, FIN | ACK))
            else:
                for frame in conv.close(by_client):
                    writer.write(event.ts, frame)
            del self._tcp[stream.id]

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if not self._writers:
            self._writer(_IP)  # an empty but valid capture
        for writer in self._writers.values():
            writer.close()
