"""Pcap sink (``-w FILE.pcap`` and ``mbmon export LOG.mcap -o FILE.pcap``), and
its pcapng form (``.pcapng``: one file, the changes marked as comments in it).

A thin listener over :class:`mbmon.io.pcap.ChunkWriter`, which owns
how captured bytes are re-wrapped so Wireshark decodes them (TCP conversations
with consistent numbers, original endpoints and times, handshakes, FIN/RST,
gaps; UDP datagrams; RS485 bus bytes as link type 147). This module owns the
file choice: a classic pcap holds one link type, so the first chunk decides the
file's type; if the session also has the other kind of stream, those packets go
to a companion file next to it: ``NAME.rtu.pcap`` (link type 147) or
``NAME.tcp.pcap`` (Ethernet). Every hub tick flushes the file, so a live
``-w x.pcap`` has every packet on disk within a second. It also says, on
closing, what a Wireshark user must know (:meth:`PcapSink.notes`): server
ports rewritten to 502, the exact option that makes Wireshark decode a port
kept as it was, bytes the capture lost where the file numbers on, and how many
packets had a capture time a pcap cannot hold (they are written at the
previous packet's time); and it names the file when writing fails (a full disk).
"""

from __future__ import annotations

import sys
from pathlib import Path

from mbmon.io.pcap import LINKTYPE_USER0, ChunkWriter
from mbmon.model import Chunk, Direction, Event, Transport
from mbmon.sinks.base import SinkBase, SinkContext
from mbmon.timefmt import epoch_text

#: the tshark option that makes Wireshark decode link type 147 (USER0) as Modbus RTU
RTU_OPTION = 'uat:user_dlts:"User 0 (DLT=147)","mbrtu","0","","0",""'

#: Wireshark's dissector and port table of each IP transport (for ``-d``, Decode As)
_DECODE_AS: dict[Transport, tuple[str, str, str]] = {
    Transport.TCP: ("tcp", "mbtcp", "Modbus/TCP"),
    Transport.UDP: ("udp", "mbudp", "Modbus/UDP"),
    Transport.RTU_OVER_TCP: ("tcp", "mbrtu", "Modbus RTU"),
    Transport.RTU_OVER_UDP: ("udp", "mbrtu", "Modbus RTU"),
}


def decode_as_options(kept: set[tuple[Transport, int]]) -> list[str]:
    """The tshark options (``-d tcp.port==1502,mbtcp`` ...) that make Wireshark decode
    the server ports ``kept`` (``(transport, port)``) as Modbus, in a stable order."""
    options = []
    for transport, port in sorted(kept, key=lambda k: (k[0].value, k[1])):
        table, dissector, _name = _DECODE_AS[transport]
        options += ["-d", f"{table}.port=={port},{dissector}"]
    return options


class PcapSink(SinkBase):
    """Raw chunks and connect/disconnect events out as a pcap Wireshark can dissect.

    ``adu_segments``: one Modbus/TCP ADU per TCP segment (the export's default)
    instead of the original segmentation; bytes the capture lost are then numbered
    over; RTU buses one frame per record (framed with the context's ``baud`` and
    ``timeout``, as the records were), instead of one record per serial read.
    ``server_port``: write every Modbus/TCP and Modbus/UDP server port as this one
    (the export's default: 502, which Wireshark decodes with no option).
    ``pcapng``: write pcapng (:class:`PcapngSink`) instead.
    """

    def __init__(
        self,
        path: str | Path,
        ctx: SinkContext | None = None,
        *,
        adu_segments: bool = False,
        server_port: int | None = None,
        pcapng: bool = False,
    ) -> None:
        self.path = Path(path)
        self.ctx = ctx
        self._closed = False
        try:
            # fail early (bad directory, no permission) rather than at the first chunk
            self.path.open("ab").close()
            self._writer = ChunkWriter(
                self.path,
                pcapng=pcapng,
                nanosecond=False,
                adu_segments=adu_segments,
                companion=self._companion_path,
                server_port=server_port,
                baudrate=ctx.baud if ctx is not None else None,
                silence=ctx.timeout if ctx is not None else None,
            )
        except OSError as exc:
            raise self._named(exc) from exc

    def _companion_path(self, linktype: int) -> Path:
        kind = "rtu" if linktype == LINKTYPE_USER0 else "tcp"
        return self.path.with_name(f"{self.path.stem}.{kind}.pcap")

    def _named(self, exc: OSError) -> OSError:
        """``exc`` with this sink's file named (the hub reports ``FILE: reason``)."""
        target = exc.filename or str(self.path)
        return OSError(exc.errno, exc.strerror or str(exc), str(target))

    @property
    def companion(self) -> Path | None:
        """The second file, when the session mixed RTU buses and IP streams."""
        return self._writer.companion_path

    @property
    def ports_kept(self) -> set[tuple[Transport, int]]:
        """Server ports written as they were that Wireshark does not decode by itself."""
        return set(self._writer.ports_kept)

    def notes(self) -> list[str]:
        """What a Wireshark user of this file must know, one sentence each (printed on
        closing): ports rewritten, the option a kept port needs, bytes the capture lost."""
        writer = self._writer
        out = []
        for (transport, port), new in sorted(
            writer.ports_rewritten.items(), key=lambda kv: (kv[0][0].value, kv[0][1])
        ):
            name = _DECODE_AS[transport][2]
            out.append(
                f"{self.path}: {name} server port {port} written as {new}, which Wireshark "
                f"decodes as {name} with no option"
            )
        kept = writer.ports_kept
        if kept:
            ports = ", ".join(
                f"{_DECODE_AS[t][0].upper()} {p}"
                for t, p in sorted(kept, key=lambda k: (k[0].value, k[1]))
            )
            options = " ".join(decode_as_options(kept))
            out.append(
                f"{self.path}: Wireshark decodes Modbus only on port 502 (TCP/UDP) by itself; "
                f"for {ports}: tshark -r {self.path} {options} (Wireshark: Analyze > "
                "Decode As..., the port, as the dissector named after the comma)"
            )
        if writer.bus_records:
            rtu_file = self.companion if writer.linktype != LINKTYPE_USER0 else None
            bus_file = rtu_file or self.path
            out.append(
                f"{bus_file}: RS485 bus records have link type 147 (USER0); Wireshark decodes "
                f"them as Modbus RTU with: tshark -r {bus_file} -o '{RTU_OPTION}' (Wireshark: "
                "Preferences > Protocols > DLT_USER, User 0 (DLT=147), payload protocol mbrtu)"
            )
        if writer.losses:
            lost = sum(n for _ts, _stream, _direction, n in writer.losses)
            ts, stream, direction, _n = writer.losses[0]
            way = "server to client" if direction == Direction.S2C.value else "client to server"
            out.append(
                f"{self.path}: the capture lost {lost} byte(s) of Modbus/TCP in "
                f"{len(writer.losses)} place(s) (first at {epoch_text(ts)} s, {stream.client} "
                f"<> {stream.server}, {way}); the segments are numbered on, one ADU each, so "
                "that Wireshark dissects every ADU mbmon framed (it shows no gap there)"
            )
        return out

    @property
    def skipped(self) -> int:
        """Packets whose capture time a pcap cannot hold (written at the previous time)."""
        return self._writer.bad_times

    # ------------------------------------------------------------------ sink API

    def on_chunk(self, chunk: Chunk) -> None:
        try:
            self._writer.write(chunk)
        except OSError as exc:
            raise self._named(exc) from exc

    def on_event(self, event: Event) -> None:
        """Connect: a three-way handshake; disconnect: FIN/FIN/ACK or an RST; gap: a hole."""
        try:
            self._writer.write(event)
        except OSError as exc:
            raise self._named(exc) from exc

    def on_tick(self, now: float) -> None:
        """Time moves on (every quarter second on a live input, also while nothing
        arrives): the packets written so far reach the file."""
        if self._closed:
            return
        try:
            self._writer.flush()
        except OSError as exc:
            raise self._named(exc) from exc

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.close()
        except OSError as exc:
            raise self._named(exc) from exc
        for note in self.notes():
            print(f"mbmon: note: {note}", file=sys.stderr)
        bad = self._writer.bad_times
        if bad:
            first = epoch_text(self._writer.first_bad_time or 0.0)
            print(
                f"mbmon: {self.path}: {bad} packet(s) had a capture time a pcap cannot hold "
                f"(first: {first} s); written at the previous packet's time",
                file=sys.stderr,
            )


class PcapngSink(PcapSink):
    """The same packets as :class:`PcapSink`, as pcapng (``-w x.pcapng``, ``export -o
    x.pcapng``): one file for IP streams and buses alike, and what the export changed
    is marked in it, not only noted on stderr: a comment on the first packet of a
    stream whose server port was rewritten, on the first segment after bytes the
    capture lost, and a summary in the section header."""

    def __init__(
        self,
        path: str | Path,
        ctx: SinkContext | None = None,
        *,
        adu_segments: bool = False,
        server_port: int | None = None,
    ) -> None:
        super().__init__(path, ctx, adu_segments=adu_segments, server_port=server_port, pcapng=True)
