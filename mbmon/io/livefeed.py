"""``replay --foxglove``: what replay prints, served live to Foxglove."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any


class ReplayFeed:
    """``replay --foxglove``: what replay prints, served live (paced by ``--speed``).

    Stored lines: the log's own messages of each printed record, on every topic
    (and, unfiltered, its raw chunks and the writer's stats), read alongside in
    file order from a second reader of the log. ``--redecode``: the records as
    a log of the re-decode would hold them (:class:`~mbmon.sinks.foxglove.FoxgloveFeed`).
    """

    def __init__(self, feed: Any, log: Any, redecode: bool, everything: bool) -> None:
        self.feed = feed
        self.everything = everything
        self._log: Any = None
        self._messages: Iterator[Any] | None = None
        self._held: tuple[int | None, Any] | None = None
        if not redecode:
            from mbmon.io.mcap.reader import McapLog

            try:
                self._log = McapLog(log.path)
            except Exception:
                feed.close()
                raise
            self._messages = self._log.messages(feed.topics)

    @property
    def chunks(self) -> Any:
        """A hub listener that serves raw chunks (unfiltered re-decodes only)."""
        feed, everything = self.feed, self.everything

        class _Chunks:
            name = "foxglove"

            def on_chunk(self, chunk: Any) -> None:
                if everything:
                    feed.on_chunk(chunk)

        return _Chunks()

    name = "foxglove"

    def on_records(self, records: list[Any]) -> None:
        """Listener hook: serve each record replay prints (after its filters)."""
        for record in records:
            self.serve(record)

    def serve(self, made: Any) -> None:
        """Serve one printed row: a re-decoded record, or a stored record's messages."""
        if self._messages is None:
            self.feed.on_records([made])
            return
        self._serve_upto(made.index)

    def finish(self) -> None:
        """Unfiltered: what the log holds after the last record (raw chunks, stats)."""
        if self._messages is not None and self.everything:
            self._serve_upto(None)

    def _serve_upto(self, index: int | None) -> None:
        """Serve the stored messages of record ``index`` (skip those of earlier records)."""
        assert self._messages is not None
        while True:
            if self._held is None:
                msg = next(self._messages, None)
                if msg is None:
                    return
                self._held = (_record_index(msg), msg)
            of, msg = self._held
            if index is not None and of is not None and of > index:
                return
            self._held = None
            if of == index if of is not None else self.everything:
                data = _as_served(msg)
                if data is not None:
                    self.feed.publish(msg.topic, msg.log_time, data)

    def close(self) -> None:
        try:
            self.feed.close()
        finally:
            if self._log is not None:
                self._log.close()


def _record_index(msg: Any) -> int | None:
    """Which record a stored message belongs to (``None``: raw chunks, the writer's stats)."""
    from mbmon.io.mcap.layout import TOPIC_MONITOR
    from mbmon.io.mcap.reader import LogError

    try:
        data = msg.json()
    except LogError:
        return None
    if not isinstance(data, dict):
        return None
    index = data.get("line") if msg.topic == TOPIC_MONITOR else data.get("index")
    return index if isinstance(index, int) and not isinstance(index, bool) else None


def _as_served(msg: Any) -> bytes | None:
    """A stored message as the feed's channel carries it: as stored, except a JSON
    message of a log before format 3 on a topic the feed serves in protobuf, which is
    made the message format 3 stores (``None``: a damaged payload, not served)."""
    from mbmon.io.mcap.layout import PROTO_TOPICS, proto_payload
    from mbmon.io.mcap.reader import LogError

    if msg.decoder is not None or msg.topic not in PROTO_TOPICS:
        return bytes(msg.raw)
    try:
        return proto_payload(msg.topic, msg.json())
    except (LogError, TypeError, ValueError):
        return None
