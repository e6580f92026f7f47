"""The stream ids of one run: one allocator (:class:`StreamIds`, the hub's
``stream_ids``) that every source of the run takes its ids from, so that two
sources' streams never share one (two capture files of one ``read``, a proxy and
a sniffer, two logs), and :class:`RecordedStreams`, which puts the ids a source
already carries (an MCAP log's recorded streams) on the run's."""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator
from dataclasses import replace

from mbmon.model import Chunk, Event, Stream

__all__ = ["RecordedStreams", "StreamIds"]

Item = Chunk | Event


class StreamIds:
    """The one allocator of a run's stream ids (thread-safe): every source of the run
    takes its ids here, so no two sources' streams share one.

    :meth:`new` gives the lowest id nobody holds; :meth:`claim` keeps an id a source
    already carries (a log's recorded ids) when it is still free, so one log replayed
    alone keeps the ids it was recorded with, and gives a new one when another
    source holds it.
    """

    def __init__(self) -> None:
        self._next = 0
        self._taken: set[int] = set()
        self._lock = threading.Lock()

    def new(self) -> int:
        """An id no source of the run holds."""
        with self._lock:
            return self._take_next()

    def claim(self, wanted: int) -> int:
        """``wanted`` when no source holds it yet, else a new id."""
        with self._lock:
            if wanted >= 0 and wanted not in self._taken:
                self._taken.add(wanted)
                return wanted
            return self._take_next()

    def _take_next(self) -> int:
        sid = self._next
        while sid in self._taken:
            sid += 1
        self._taken.add(sid)
        self._next = sid + 1
        return sid


class RecordedStreams:
    """One source's own stream ids (an MCAP log's recorded ``/modbus/raw`` streams) put
    on the run's: each id the source carries becomes one of the hub's
    (:meth:`StreamIds.claim`), the same one for every item of the source, and an
    event naming another stream (a proxy's ``answers_on``) names the mapped one."""

    def __init__(self, ids: StreamIds) -> None:
        self._ids = ids
        self._map: dict[int, int] = {}
        self._streams: dict[Stream, Stream] = {}

    def stream_id(self, recorded: int) -> int:
        """The run's id of the source's stream ``recorded``."""
        sid = self._map.get(recorded)
        if sid is None:
            sid = self._map[recorded] = self._ids.claim(recorded)
        return sid

    def stream(self, stream: Stream) -> Stream:
        """``stream`` with the run's id (the same object for every item of it)."""
        mapped = self._streams.get(stream)
        if mapped is None:
            sid = self.stream_id(stream.id)
            mapped = stream if sid == stream.id else replace(stream, id=sid)
            self._streams[stream] = mapped
        return mapped

    def item(self, item: Item) -> Item:
        """``item`` on the run's streams."""
        stream = item.stream
        if isinstance(item, Chunk):
            assert stream is not None
            mapped = self.stream(stream)
            return item if mapped is stream else replace(item, stream=mapped)
        mapped_stream = self.stream(stream) if stream is not None else None
        info = item.info
        other = info.get("answers_on")
        if type(other) is int and self.stream_id(other) != other:
            info = {**info, "answers_on": self.stream_id(other)}
        if mapped_stream is stream and info is item.info:
            return item
        return replace(item, stream=mapped_stream, info=info)

    def items(self, items: Iterable[Item]) -> Iterator[Item]:
        """Every item of ``items`` on the run's streams."""
        item_of = self.item
        for item in items:
            yield item_of(item)
