"""Pcap sink (``-w FILE.pcap`` and ``mbmon export LOG.mcap -o FILE.pcap``).

A thin listener over :class:`mbmon.sources.pcapwrite.ChunkWriter`, which owns
how captured bytes are re-wrapped so Wireshark decodes them (TCP conversations
with consistent numbers, original endpoints and times, handshakes, FIN/RST,
gaps; UDP datagrams; RS485 bus bytes as link type 147). This module owns the
file choice: a classic pcap holds one link type, so the first chunk decides the
file's type; if the session also has the other kind of stream, those packets go
to a companion file next to it: ``NAME.rtu.pcap`` (link type 147) or
``NAME.tcp.pcap`` (Ethernet). Every hub tick flushes the file, so a live
``-w x.pcap`` has every packet on disk within a second. It also says, on
closing, how many packets had a capture time a pcap cannot hold (they are
written at the previous packet's time), and names the file when writing fails
(a full disk).
"""

from __future__ import annotations

import sys
from pathlib import Path

from mbmon.model import Chunk, Event
from mbmon.sinks.base import SinkBase, SinkContext
from mbmon.sources.pcapwrite import LINKTYPE_USER0, ChunkWriter
from mbmon.timefmt import epoch_text


class PcapSink(SinkBase):
    """Raw chunks and connect/disconnect events out as a pcap Wireshark can dissect.

    ``adu_segments``: one Modbus/TCP ADU per TCP segment (the export's default)
    instead of the original segmentation.
    """

    def __init__(
        self, path: str | Path, ctx: SinkContext | None = None, *, adu_segments: bool = False
    ) -> None:
        self.path = Path(path)
        self.ctx = ctx
        self._closed = False
        try:
            # fail early (bad directory, no permission) rather than at the first chunk
            self.path.open("ab").close()
            self._writer = ChunkWriter(
                self.path,
                nanosecond=False,
                adu_segments=adu_segments,
                companion=self._companion_path,
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
        bad = self._writer.bad_times
        if bad:
            first = epoch_text(self._writer.first_bad_time or 0.0)
            print(
                f"mbmon: {self.path}: {bad} packet(s) had a capture time a pcap cannot hold "
                f"(first: {first} s); written at the previous packet's time",
                file=sys.stderr,
            )
