"""Files as sources of the hub: packet captures, raw RTU bus dumps and MCAP logs.

Each class implements the source contract (:mod:`mbmon.sources.base`) over the
readers that exist: :func:`~mbmon.sources.pcapfile.read_capture` (pcap, pcapng,
gzip), :func:`~mbmon.sources.rawfile.read_rtu_raw` (bytes as read from an RS485
line) and :func:`~mbmon.io.replay.raw_items` (the ``/modbus/raw`` topic of an
mbmon MCAP log: the input of the run that wrote it, for ``replay --redecode``,
``export`` and ``info``). A regular file is a ``"file"`` source (read as fast as
it goes); a pipe, FIFO, socket or character device is a ``"stream"`` source
(read as it comes while the hub keeps ticking). :meth:`open` checks that the file
can be read, so a missing or foreign file is one line (:class:`SourceError`)
before any output exists.
"""

from __future__ import annotations

import itertools
import os
import stat
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mbmon.sources.base import BaseSource, SourceError, SourceMode
from mbmon.sources.pcapfile import CaptureConfig, CaptureError, read_capture
from mbmon.sources.rawfile import read_rtu_raw

if TYPE_CHECKING:
    from mbmon.hub import Hub, Item

__all__ = ["CaptureFileSource", "McapLogSource", "RawRtuSource", "is_stream_input"]


def is_stream_input(path: str | Path) -> bool:
    """A pipe, FIFO, socket or character device: read as it comes, shown as it comes."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    return stat.S_ISFIFO(mode) or stat.S_ISCHR(mode) or stat.S_ISSOCK(mode)


def _mode(path: str | Path) -> SourceMode:
    return "stream" if is_stream_input(path) else "file"


class CaptureFileSource(BaseSource):
    """A pcap or pcapng file (``-``: stdin), its Modbus traffic through the dissector.

    :attr:`capture_stats` is filled with the reader's counters when the items end
    (packets, bytes, the dissector's figures; see ``read_capture``).
    """

    def __init__(
        self,
        path: str | Path,
        config: CaptureConfig | None = None,
        *,
        progress: Callable[[int, int], None] | None = None,
    ) -> None:
        super().__init__()
        self.path = "/dev/stdin" if str(path) == "-" else str(path)
        self.name = self.path
        self.mode = _mode(self.path)
        self.config = config or CaptureConfig()
        self.progress = progress
        self.capture_stats: dict[str, Any] = {}
        self._items: Iterator[Item] | None = None
        self._reader: Iterator[Item] | None = None  # read_capture's generator

    def open(self, hub: Hub) -> None:
        """Open the capture and read its first record (a file that is no capture, or
        damaged at its start, fails here: :class:`SourceError`)."""
        super().open(hub)
        try:
            items = read_capture(
                self.path,
                self.config,
                progress=self.progress,
                stats=self.capture_stats,
                new_stream=hub.new_stream,  # several inputs of one run: ids of their own
            )
            first = next(items, None)
        except CaptureError as exc:
            raise SourceError(str(exc)) from None
        self._reader = items
        self._items = itertools.chain(() if first is None else (first,), items)

    def items(self) -> Iterable[Item]:
        """The capture's chunks and events, in capture order."""
        return self._items if self._items is not None else ()

    def stop(self) -> None:
        """Close the capture (idempotent; what was not read is left unread). A reader
        thread still inside the capture (a pipe, at Ctrl-C) keeps it: it ends with
        the process."""
        reader, self._reader = self._reader, None
        close = getattr(reader, "close", None)
        if close is not None and not getattr(reader, "gi_running", False):
            try:
                close()
            except ValueError:  # it started running meanwhile: its thread keeps it
                pass

    def stats(self) -> dict[str, Any]:
        """The reader's counters (complete once the items ended)."""
        return dict(self.capture_stats)

    def summary(self) -> list[str]:
        """Packets read, and how many carried Modbus."""
        s = self.capture_stats
        if not s:
            return []
        return [
            f"{s.get('packets', 0)} packets, {s.get('modbus_packets', 0)} Modbus packets, "
            f"{s.get('streams', 0)} streams"
        ]


class RawRtuSource(BaseSource):
    """A raw RS485 dump (no timestamps): one untimed RTU bus stream, its id the hub's."""

    def __init__(self, path: str | Path, *, chunk_size: int = 4096) -> None:
        super().__init__()
        self.path = "/dev/stdin" if str(path) == "-" else str(path)
        self.name = self.path
        self.mode = _mode(self.path)
        self.chunk_size = chunk_size
        self._items: Iterator[Item] | None = None
        self.bytes = 0

    def open(self, hub: Hub) -> None:
        """Open the dump (:class:`SourceError` when it cannot be)."""
        super().open(hub)
        try:
            chunks = read_rtu_raw(self.path, self.chunk_size, stream_id=hub.new_stream_id())
        except CaptureError as exc:
            raise SourceError(str(exc)) from None
        self._items = self._counted(chunks)

    def _counted(self, chunks: Iterator[Any]) -> Iterator[Item]:
        for chunk in chunks:
            self.bytes += len(chunk.data)
            yield chunk

    def items(self) -> Iterable[Item]:
        """The dump's bytes as chunks of the bus stream (ts 0.0: untimed)."""
        return self._items if self._items is not None else ()

    def stats(self) -> dict[str, Any]:
        """Bytes read so far."""
        return {"bytes": self.bytes}

    def summary(self) -> list[str]:
        """Bytes read."""
        return [f"{self.bytes} bytes read from {self.name}"]


class McapLogSource(BaseSource):
    """An mbmon MCAP log's recorded input (``/modbus/raw``: chunks and source events),
    for a run that decodes it again. Its stream ids are the recorded ones where no
    other source of the run holds them (one log alone keeps them all), else new ones
    of the hub's (:meth:`~mbmon.hub.Hub.recorded_streams`).

    :attr:`log` is the open :class:`~mbmon.io.mcap.reader.McapLog` after :meth:`open`
    (its metadata: the recorded options and profiles); :meth:`stop` closes it.
    """

    def __init__(self, path: str | Path) -> None:
        super().__init__()
        self.path = str(path)
        self.name = self.path
        self.mode = "file"
        self.log: Any = None

    def open(self, hub: Hub) -> None:
        """Open the log (:class:`SourceError` when it is missing or no MCAP log)."""
        from mbmon.io.mcap.reader import LogError, McapLog

        super().open(hub)
        try:
            self.log = McapLog(self.path)
        except LogError as exc:
            raise SourceError(str(exc)) from None

    def items(self) -> Iterable[Item]:
        """The recorded chunks and events, in capture order (damaged ones left out)."""
        if self.log is None:
            return ()
        from mbmon.io.replay import raw_items

        if self.hub is None:
            return raw_items(self.log)
        return self.hub.recorded_streams().items(raw_items(self.log))

    def stop(self) -> None:
        """Close the log (idempotent)."""
        if self.log is not None:
            self.log.close()

    def stats(self) -> dict[str, Any]:
        """How far reading got (messages, damaged ones left out)."""
        if self.log is None:
            return {}
        status = self.log.status
        return {"messages": status.messages, "skipped": len(status.skipped)}

    def summary(self) -> list[str]:
        """The state of the file and the damaged messages left out, in words."""
        if self.log is None:
            return []
        status = self.log.status
        return [status.describe(), *status.skipped_lines()]
