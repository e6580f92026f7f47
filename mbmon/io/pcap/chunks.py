"""Chunks and events back into a capture: :class:`ChunkWriter`, mbmon's one pcap
writer (``-w x.pcap`` and ``export -o x.pcap`` through
:class:`mbmon.sinks.pcap.PcapSink`, a thin listener over it): one conversation per
TCP stream (optionally one ADU per segment), datagrams for UDP, link type 147
records for RTU bus bytes; reading its output with
:func:`mbmon.sources.pcapfile.read_capture` gives the same chunks and events.
"""

from __future__ import annotations

import datetime
import ipaddress
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO

from mbmon.io.pcap.files import PcapngWriter, PcapWriter
from mbmon.io.pcap.packets import (
    ACK,
    FIN,
    LINKTYPE_ETHERNET,
    LINKTYPE_USER0,
    MODBUS_PORT,
    TcpConversation,
    join_endpoint,
    parse_endpoint,
    udp_frame,
)
from mbmon.model import Chunk, Direction, Event, EventKind, Frame, Stream, Transport
from mbmon.timefmt import epoch_text


def _utc_text(ts: float) -> str:
    """``ts`` as a UTC date and time with microseconds (epoch seconds out of range)."""
    try:
        when = datetime.datetime.fromtimestamp(ts, datetime.UTC)
    except (ValueError, OverflowError, OSError):
        return f"{epoch_text(ts)} s"
    return when.strftime("%Y-%m-%d %H:%M:%S.%f UTC")


class ChunkWriter:
    """Chunks and events back into a capture that :func:`read_capture` reads as the
    same chunks and events: the one pcap writer (``-w x.pcap``, ``export -o x.pcap``).

    TCP streams become Ethernet/IP/TCP conversations with consistent numbers: a
    CONNECT event writes the three-way handshake, each chunk one segment (cut in
    pieces of at most 32 KiB), a GAP skips its bytes (the peer then acknowledges
    them, so a re-read reports the same gap), a DISCONNECT writes FIN-FIN-ACK or a
    RST from the side that sent it (an idle expiry, where the dissector merely
    stopped watching a quiet flow, writes nothing). UDP chunks become datagrams; RTU bus chunks
    become link type 147 records. Other events are not packets and are skipped.
    Stream endpoints that are not ``IP:PORT`` get made-up addresses derived from
    the stream id.

    ``adu_segments``: Modbus/TCP streams are written one ADU per TCP segment
    (framed by :class:`~mbmon.protocol.mbap.MbapDecoder`; bytes it cannot frame
    become segments of their own, in order), each at the time of the chunk that
    carried its last byte, so that Wireshark dissects every ADU even where the
    original segmentation split an MBAP header. Every byte is written once. A
    GAP (bytes the capture lost) is then no hole in the sequence numbers: with
    one ADU per segment there is nothing to reassemble, and a hole would stop
    Wireshark's reassembly for the rest of the connection; the segments are
    numbered contiguously and the loss is listed in :attr:`losses`. RTU bus
    streams are written one frame per link type 147 record (framed by
    :class:`~mbmon.protocol.rtu.RtuDecoder` with ``baudrate`` and ``silence``, as
    the pipeline frames them; each run of noise a record of its own), at the
    frame's own time, so that a serial read holding a request and its answer
    becomes two records Wireshark decodes.

    ``server_port``: the server port of every Modbus/TCP and Modbus/UDP stream
    is written as this port (502: what Wireshark decodes as Modbus with no
    option); :attr:`ports_rewritten` maps each original port to it. Server
    ports written as they were and that Wireshark does not decode as Modbus by
    itself (not 502, or RTU carried over TCP/UDP) are in :attr:`ports_kept`.

    A pcap file has one link type, so with ``pcapng=False`` the first chunk fixes
    it (Ethernet, or 147 for a bus) and a chunk needing the other goes to the file
    ``companion(linktype)`` names, or raises ValueError without one; pcapng holds
    both (one interface per bus). A capture time the file cannot hold (negative,
    beyond 2106 for pcap, NaN...) is written as the previous packet's time and
    counted in :attr:`bad_times` (the first in :attr:`first_bad_time`).
    """

    MAX_SEGMENT = 32768  # larger chunks are cut into several segments (IPv4 length limit)
    NOISE_SEGMENT = 7  # unframable bytes (adu_segments): too short for an MBAP header

    def __init__(
        self,
        out: str | Path | BinaryIO,
        *,
        pcapng: bool = False,
        nanosecond: bool = True,
        adu_segments: bool = False,
        companion: Callable[[int], str | Path] | None = None,
        server_port: int | None = None,
        baudrate: int | None = None,
        silence: float | None = None,
    ) -> None:
        self._out = out
        self._nanosecond = nanosecond
        self._pcapng: PcapngWriter | None = PcapngWriter(out) if pcapng else None
        self._pcap: PcapWriter | None = None
        self._pcap_link: int | None = None
        self._other: PcapWriter | None = None
        self._companion = companion
        self.companion_path: Path | None = None
        self._ether_iface: int | None = None
        self._bus_ifaces: dict[int, int] = {}
        self._tcp: dict[int, TcpConversation] = {}
        self._adu_segments = adu_segments
        self._server_port = server_port
        self._baudrate = baudrate
        self._silence = silence
        self._bus_framers: dict[int, Any] = {}  # stream id -> its RtuDecoder, with adu_segments
        self._ends: dict[int, tuple[str, str]] = {}  # stream id -> endpoints as written
        #: (transport, original server port) -> the port written instead
        self.ports_rewritten: dict[tuple[Transport, int], int] = {}
        #: (transport, server port) written as they were, that Wireshark does not
        #: decode as Modbus with no option
        self.ports_kept: set[tuple[Transport, int]] = set()
        # (transport, host, port as written) -> the port it stands for: two servers of
        # one host (a proxy's own answers beside its robot's) never become one endpoint
        self._claimed: dict[tuple[Transport, str, int], int] = {}
        #: bytes the capture lost, numbered over (adu_segments): (time, stream,
        #: direction value, bytes), in order
        self.losses: list[tuple[float, Stream, str, int]] = []
        #: link type 147 records written (RTU bus bytes)
        self.bus_records = 0
        # pcapng packet comments waiting for their packet: a stream's first (its
        # server port rewritten), a direction's next segment (bytes lost before it)
        self._stream_notes: dict[int, str] = {}
        self._loss_notes: dict[tuple[int, bool], list[str]] = {}
        # (stream id, direction) -> (stream, its MBAP decoder), with adu_segments
        self._framers: dict[tuple[int, Direction], tuple[Stream, Any]] = {}
        # the range of times the file holds: pcap has 32-bit seconds; pcapng 64-bit units
        self._max_ts = 1.8e10 if pcapng else 4294967295.0
        self._last_ts = 0.0
        self.bad_times = 0
        self.first_bad_time: float | None = None

    @property
    def linktype(self) -> int | None:
        """The link type of the classic pcap file (the first packet's), ``None`` before
        the first packet or for pcapng (which holds both)."""
        return self._pcap_link

    def _time(self, ts: float) -> float:
        """``ts``, or the previous packet's time when the file cannot hold it."""
        if 0.0 <= ts < self._max_ts:
            self._last_ts = ts
            return ts
        self.bad_times += 1
        if self.first_bad_time is None:
            self.first_bad_time = ts
        return self._last_ts

    def _emit(
        self, ts: float, frame: bytes, linktype: int, stream_id: int, comments: Sequence[str] = ()
    ) -> None:
        """Write one packet of ``stream_id`` (pcapng: with ``comments``, and the
        stream's own note before them on its first packet)."""
        ts = self._time(ts)
        note = self._stream_notes.pop(stream_id, None)
        if note is not None:
            comments = [note, *comments]
        if linktype == LINKTYPE_USER0:
            self.bus_records += 1
        if self._pcapng is not None:
            if linktype == LINKTYPE_USER0:
                iface = self._bus_ifaces.get(stream_id)
                if iface is None:
                    iface = self._bus_ifaces[stream_id] = self._pcapng.add_interface(
                        LINKTYPE_USER0, tsresol=9
                    )
            else:
                if self._ether_iface is None:
                    self._ether_iface = self._pcapng.add_interface(LINKTYPE_ETHERNET, tsresol=9)
                iface = self._ether_iface
            self._pcapng.write(ts, frame, interface=iface, comments=comments)
            return
        if self._pcap is None:
            self._pcap = PcapWriter(self._out, linktype, nanosecond=self._nanosecond)
            self._pcap_link = linktype
        elif linktype != self._pcap_link:
            if self._companion is None:
                raise ValueError(
                    f"a pcap file holds one link type ({self._pcap_link}); "
                    f"link type {linktype} needs pcapng"
                )
            if self._other is None:
                self.companion_path = Path(self._companion(linktype))
                self._other = PcapWriter(self.companion_path, linktype, nanosecond=self._nanosecond)
            self._other.write(ts, frame)
            return
        self._pcap.write(ts, frame)

    def _endpoints(self, stream: Stream) -> tuple[str, str]:
        """The stream's endpoints as written: its own or made-up ones (see
        :meth:`_stream_endpoints`), the server port rewritten to ``server_port``
        for Modbus/TCP and Modbus/UDP."""
        ends = self._ends.get(stream.id)
        if ends is not None:
            return ends
        client, server = self._stream_endpoints(stream)
        host, port = parse_endpoint(server)
        mbap = stream.transport in (Transport.TCP, Transport.UDP)
        if mbap and self._server_port is not None:
            claim = self._claimed.setdefault((stream.transport, host, self._server_port), port)
            if claim != port:  # another server of this host is written there: keep this one
                self.ports_kept.add((stream.transport, port))
            elif port != self._server_port:
                self.ports_rewritten[(stream.transport, port)] = self._server_port
                self._stream_notes[stream.id] = (
                    f"mbmon: server port {port} in the original capture, written as "
                    f"{self._server_port}"
                )
                server = join_endpoint(host, self._server_port)
        elif not mbap or port != MODBUS_PORT:
            self.ports_kept.add((stream.transport, port))
        ends = self._ends[stream.id] = (client, server)
        return ends

    @staticmethod
    def _stream_endpoints(stream: Stream) -> tuple[str, str]:
        """The stream's endpoints, or made-up ones when they are not ``IP:PORT``."""
        try:
            for endpoint in (stream.client, stream.server):
                ipaddress.ip_address(parse_endpoint(endpoint)[0])
        except ValueError:
            sid = stream.id & 0xFFFF
            return (
                f"10.200.{sid >> 8}.{sid & 0xFF}:{49152 + stream.id % 16384}",
                f"10.201.{sid >> 8}.{sid & 0xFF}:502",
            )
        return stream.client, stream.server

    def _conversation(self, stream: Stream) -> TcpConversation:
        conv = self._tcp.get(stream.id)
        if conv is None:
            client, server = self._endpoints(stream)
            conv = self._tcp[stream.id] = TcpConversation(
                client,
                server,
                client_isn=(stream.id * 2654435761 + 1000) & 0xFFFFFFFF,
                server_isn=(stream.id * 2246822519 + 5000) & 0xFFFFFFFF,
            )
        return conv

    def write(self, item: Chunk | Event) -> None:
        """One chunk or event, in the order the reader produced them."""
        stream = item.stream
        if stream is None:
            return
        tcp = stream.transport in (Transport.TCP, Transport.RTU_OVER_TCP)
        if isinstance(item, Event):
            if tcp:
                if self._adu_segments:
                    # a gap ends what its own direction holds; the other one goes on
                    gap = item.kind is EventKind.GAP
                    self._flush_adus(stream, item.ts, item.info.get("direction") if gap else None)
                for frame in self._event_frames(item, stream, self._conversation(stream)):
                    self._emit(item.ts, frame, LINKTYPE_ETHERNET, stream.id)
            return
        from_client = item.direction is not Direction.S2C
        if tcp:
            if self._adu_segments and stream.transport is Transport.TCP:
                for piece, framed in self._adus(stream, item.direction, item.data, item.ts):
                    self._adu_segment(stream, from_client, piece, framed, item.ts)
            else:
                self._segments(stream, from_client, item.data, item.ts)
            return
        if stream.transport in (Transport.UDP, Transport.RTU_OVER_UDP):
            client, server = self._endpoints(stream)
            (cip, cport), (sip, sport) = parse_endpoint(client), parse_endpoint(server)
            if from_client:
                frame = udp_frame(LINKTYPE_ETHERNET, cip, sip, cport, sport, item.data)
            else:
                frame = udp_frame(LINKTYPE_ETHERNET, sip, cip, sport, cport, item.data)
            self._emit(item.ts, frame, LINKTYPE_ETHERNET, stream.id)
            return
        if self._adu_segments:  # a serial bus: one frame (or noise run) per record
            for frame in self._bus_framer(stream).feed(item.data, item.ts):
                self._emit(frame.ts, frame.raw, LINKTYPE_USER0, stream.id)
            return
        self._emit(item.ts, item.data, LINKTYPE_USER0, stream.id)  # a serial bus, as read

    def _bus_framer(self, stream: Stream) -> Any:
        """The RTU decoder that frames the records of bus ``stream`` (adu_segments)."""
        decoder = self._bus_framers.get(stream.id)
        if decoder is None:
            from mbmon.protocol.rtu import RtuDecoder

            decoder = self._bus_framers[stream.id] = RtuDecoder(
                stream, Direction.BUS, baudrate=self._baudrate, silence=self._silence
            )
        return decoder

    def _segments(self, stream: Stream, from_client: bool, data: bytes, ts: float) -> None:
        """``data`` as TCP segments of at most :attr:`MAX_SEGMENT` bytes."""
        conv = self._conversation(stream)
        comments = self._loss_notes.pop((stream.id, from_client), [])
        for start in range(0, max(len(data), 1), self.MAX_SEGMENT):
            frame = conv.send(from_client, data[start : start + self.MAX_SEGMENT])
            self._emit(ts, frame, LINKTYPE_ETHERNET, stream.id, comments)
            comments = []

    def _adu_segment(
        self, stream: Stream, from_client: bool, data: bytes, framed: bool, ts: float
    ) -> None:
        """One framed ADU as one segment; bytes the framer could not frame in segments
        of at most :attr:`NOISE_SEGMENT` bytes. Wireshark takes a segment for Modbus/TCP
        from 8 bytes on (an MBAP header with protocol id 0) and then waits for as many
        bytes as its length field says: unframable bytes that happen to look like a
        header (a response that lost its first byte) would swallow the ADUs after
        them; shorter segments are never taken for Modbus and start no reassembly."""
        if framed:
            self._segments(stream, from_client, data, ts)
            return
        for start in range(0, len(data), self.NOISE_SEGMENT):
            self._segments(stream, from_client, data[start : start + self.NOISE_SEGMENT], ts)

    def _adus(
        self, stream: Stream, direction: Direction, data: bytes, ts: float
    ) -> list[tuple[bytes, bool]]:
        """The complete ADUs (``(bytes, True)``) and unframable runs (``(bytes, False)``)
        of one direction that ``data`` ends."""
        key = (stream.id, direction)
        entry = self._framers.get(key)
        if entry is None:
            from mbmon.protocol.mbap import MbapDecoder

            decoder = MbapDecoder(
                stream, Direction.S2C if direction is Direction.S2C else Direction.C2S
            )
            entry = self._framers[key] = (stream, decoder)
        return [(item.raw, isinstance(item, Frame)) for item in entry[1].feed(data, ts)]

    def _flush_adus(self, stream: Stream, ts: float, only: object = None) -> None:
        """Write what the framers of ``stream`` hold (before a connect or close; before
        a gap, only the framer of the gap's direction, ``only``: its value)."""
        for direction in (Direction.C2S, Direction.S2C):
            if only is not None and direction.value != only:
                continue
            entry = self._framers.pop((stream.id, direction), None)
            if entry is not None:
                for item in entry[1].flush(ts):
                    from_client = direction is not Direction.S2C
                    self._adu_segment(stream, from_client, item.raw, isinstance(item, Frame), ts)

    def _event_frames(self, event: Event, stream: Stream, conv: TcpConversation) -> list[bytes]:
        if event.kind is EventKind.CONNECT:
            return conv.open()
        if event.kind is EventKind.GAP:
            size = int(event.info.get("bytes", 0))
            if self._adu_segments and stream.transport is Transport.TCP:
                # one ADU per segment: numbered on, nothing for Wireshark to wait for
                direction = str(event.info.get("direction", Direction.C2S.value))
                self.losses.append((event.ts, stream, direction, size))
                client = direction != Direction.S2C.value
                side = "client" if client else "server"
                amount = "1 byte" if size == 1 else f"{size} bytes"
                self._loss_notes.setdefault((stream.id, client), []).append(
                    f"mbmon: {amount} of the {side}'s stream {'was' if size == 1 else 'were'} "
                    f"not captured before this segment (lost at {_utc_text(event.ts)})"
                )
                return []
            from_client = event.info.get("direction") == Direction.C2S.value
            if from_client:
                conv.client_next = (conv.client_next + size) & 0xFFFFFFFF
            else:
                conv.server_next = (conv.server_next + size) & 0xFFFFFFFF
            return [conv.ack(not from_client)]  # the peer had them: the gap shows
        if event.kind is EventKind.DISCONNECT:
            if event.info.get("how") == "idle":
                return []  # the dissector gave up on a quiet flow: nothing crossed the wire
            by_client = event.info.get("by") != "server"
            if event.info.get("how") == "rst":
                return [conv.reset(by_client)]
            if event.info.get("half_closed"):
                return [conv.segment(by_client, FIN | ACK)]
            return conv.close(by_client)
        return []

    def section_comments(self) -> list[str]:
        """What the export changed, for the pcapng section header (``shb_comment``):
        server ports rewritten and bytes lost where the segments are numbered on;
        the packets concerned carry a comment each."""
        out = [
            f"mbmon: Modbus/{transport.value.upper()} server port {port} in the original capture, "
            f"written as {new} (comment on each such stream's first packet)"
            for (transport, port), new in sorted(
                self.ports_rewritten.items(), key=lambda kv: (kv[0][0].value, kv[0][1])
            )
        ]
        if self.losses:
            lost = sum(n for _ts, _stream, _direction, n in self.losses)
            out.append(
                f"mbmon: {lost} byte(s) were not captured in {len(self.losses)} place(s); the "
                "segments are numbered contiguously, one ADU each (comment on the first "
                "segment after each loss)"
            )
        return out

    def flush(self) -> None:
        """Hand what was written so far to the OS (a live ``-w x.pcap`` on each tick);
        bytes an ADU framer holds wait for the rest of their ADU."""
        for writer in (self._pcapng, self._pcap, self._other):
            if writer is not None:
                writer.flush()

    def close(self) -> None:
        """Write what the framers hold, then finish the file(s); a capture that got
        nothing is still a valid (empty) one."""
        try:
            for stream, _ in list(self._framers.values()):
                self._flush_adus(stream, self._last_ts)
            for stream_id, decoder in list(self._bus_framers.items()):
                del self._bus_framers[stream_id]
                for frame in decoder.flush(self._last_ts):
                    self._emit(frame.ts, frame.raw, LINKTYPE_USER0, stream_id)
        finally:
            if self._pcapng is not None:
                self._pcapng.close()
                summary = self.section_comments()
                if summary and isinstance(self._out, str | Path):
                    PcapngWriter.comment_first_section(self._out, summary)
            elif self._pcap is not None:
                self._pcap.close()
            else:
                PcapWriter(self._out, LINKTYPE_ETHERNET, nanosecond=self._nanosecond).close()
            if self._other is not None:
                self._other.close()

    def __enter__(self) -> ChunkWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
