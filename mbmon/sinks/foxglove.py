"""The live Foxglove feed (``--foxglove [HOST:]PORT``): the MCAP log's topics, live.

A hub listener, like :class:`~mbmon.sinks.mcap.McapSink`, that serves over
Foxglove's WebSocket protocol (the ``foxglove-sdk`` package, an optional extra:
``pip install 'mbmon[foxglove]'``) exactly what a log of the same run holds:

- the same channels as the log (:func:`mbmon.io.mcap.layout.topics`: the
  ``/hrss`` ones only with a profile in force), advertised as soon as the
  server starts, each with its schema from ``mbmon/schemas`` (``jsonschema``)
  and JSON messages;
- the same messages, made by the one mapping of records and chunks to topics
  (:class:`mbmon.io.mcap.layout.LogLayout`), with the capture time as log
  time; only the log writer's own periodic stats events are not served.

It never slows the run: nothing is made while no client subscribes to a
channel, and ``Channel.log`` only queues (the SDK drops the oldest messages of
a slow client). If the SDK raises, the hub detaches the feed and the run goes
on. The server listens on loopback unless a host is named.

Every Foxglove client connects, whichever name of the protocol it offers: the
SDK's server accepts only ``foxglove.sdk.v1``, so it listens on a loopback port
of its own behind :class:`~mbmon.sinks.foxglove_front.SubprotocolFront`, which
listens where the user asked and lets in clients that offer only
``foxglove.websocket.v1`` (older Foxglove and Lichtblick releases) too.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from typing import Any

from mbmon.io.mcap.layout import (
    TOPIC_RAW,
    LogLayout,
    Message,
    channel_schema,
    topics,
)
from mbmon.model import Chunk, Record
from mbmon.sinks.base import SinkContext, SinkError
from mbmon.sinks.foxglove_front import SubprotocolFront

__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "INSTALL_HINT",
    "FeedUnavailable",
    "FoxgloveFeed",
    "sdk_available",
]

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
INSTALL_HINT = "pip install 'mbmon[foxglove]'"
#: seconds a closing feed leaves its clients to receive the last messages
CLOSE_GRACE = 0.25


class FeedUnavailable(SinkError):
    """The ``foxglove-sdk`` package is not installed."""


def _sdk() -> Any:
    """The ``foxglove`` module, imported only when a feed is opened."""
    try:
        import foxglove
    except ImportError:
        raise FeedUnavailable(
            f"--foxglove needs the foxglove-sdk package: {INSTALL_HINT}"
        ) from None
    return foxglove


def sdk_available() -> bool:
    """Whether ``foxglove-sdk`` can be imported (without importing it twice)."""
    try:
        _sdk()
    except FeedUnavailable:
        return False
    return True


class FoxgloveFeed:
    """Serve a run's records and chunks as the MCAP log's messages (see the module text).

    Opening starts the WebSocket server on ``host:port`` (port 0: a free port;
    :attr:`port` is the real one) and advertises the channels; a port that
    cannot be bound is a :class:`~mbmon.sinks.base.SinkError`, a missing SDK a
    :class:`FeedUnavailable`. ``channel_topics`` overrides the channel set (a
    replay serves the topics its log has); by default it is the log's for ``ctx``.
    """

    name = "foxglove"

    def __init__(
        self,
        ctx: SinkContext,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        *,
        channel_topics: Iterable[str] | None = None,
        server_name: str = "mbmon",
    ) -> None:
        foxglove = _sdk()
        self.ctx = ctx
        self.host = host
        self._context = foxglove.Context()
        try:  # the SDK's own server, on a loopback port only the front door reaches
            self._server = foxglove.start_server(
                name=server_name, host="127.0.0.1", port=0, context=self._context
            )
        except Exception as exc:  # the SDK raises RuntimeError("FoxgloveError: ...")
            text = str(exc).removeprefix("FoxgloveError: ")
            raise SinkError(f"--foxglove {_address(host, port)}: cannot listen: {text}") from None
        try:
            self._front = SubprotocolFront(host, port, int(self._server.port))
        except OSError as exc:
            self._server.stop()
            text = exc.strerror or str(exc)
            raise SinkError(f"--foxglove {_address(host, port)}: cannot listen: {text}") from None
        self.port: int = self._front.port
        if channel_topics is None:
            channel_topics = topics(bool(ctx.profiles or ctx.profile_specs))
        self._channels: dict[str, Any] = {}
        for topic in channel_topics:
            name, schema_encoding, data, encoding = channel_schema(topic)
            self._channels[topic] = foxglove.Channel(
                topic,
                schema=foxglove.Schema(name=name, encoding=schema_encoding, data=data),
                message_encoding=encoding,
                context=self._context,
            )
        # channel ids matter only inside the layout: the feed maps them back to topics
        ids = {topic: n for n, topic in enumerate(self._channels, 1)}
        self._layout = LogLayout(ctx.view, ctx.source, ids)
        self._raw = self._channels.get(TOPIC_RAW)
        self._closed = False
        #: messages handed to the SDK (to subscribed channels)
        self.messages_sent = 0

    @property
    def url(self) -> str:
        """Where Foxglove connects: ``ws://HOST:PORT``."""
        return f"ws://{_address(self.host, self.port)}"

    @property
    def topics(self) -> list[str]:
        """The advertised topics, in channel order."""
        return list(self._channels)

    def subscribed(self) -> bool:
        """Whether any client subscribes to any channel (nothing is made otherwise)."""
        return any(ch.has_sinks() for ch in self._channels.values())

    # ------------------------------------------------------------------ listener hooks

    def on_chunk(self, chunk: Chunk) -> None:
        """A captured chunk on ``/modbus/raw`` (when someone subscribes to it)."""
        raw = self._raw
        if raw is not None and raw.has_sinks():
            self._send(self._messages([chunk]))

    def on_records(self, records: list[Record]) -> None:
        """The messages of a batch of records, on their topics, in log order."""
        if self.subscribed():
            layout = self._layout
            self._send(self._messages([layout.waiting_item(r) for r in records]))

    def publish(self, topic: str, log_time: int, data: bytes) -> None:
        """One message as a log stores it (``replay`` serves a log's stored messages)."""
        channel = self._channels.get(topic)
        if channel is not None and channel.has_sinks():
            channel.log(data, log_time=log_time)
            self.messages_sent += 1

    def close(self) -> None:
        """Stop the server (clients see the connection close). Idempotent.

        With a subscriber, the SDK's sender gets :data:`CLOSE_GRACE` seconds
        first to hand over the last messages of the run (there is no flush).
        """
        if self._closed:
            return
        self._closed = True
        if self.messages_sent and self.subscribed():
            time.sleep(CLOSE_GRACE)
        for channel in self._channels.values():
            try:
                channel.close()
            except Exception:
                pass
        self._server.stop()
        self._front.close()

    # ------------------------------------------------------------------ inside

    def _messages(self, items: list[Any]) -> list[Message]:
        """The messages of waiting items, as :meth:`LogLayout.messages` makes them for one
        (no stats events: those are the log writer's), for a batch at once."""
        layout = self._layout
        totals = layout.new_totals()
        totals.next_stats = math.inf
        records, _first, _last, _totals = layout.convert(items, totals)
        return layout.split(b"".join(records))

    def _send(self, messages: list[Message]) -> None:
        channels = self._channels
        for topic, log_time, data in messages:
            channel = channels[topic]
            if channel.has_sinks():
                channel.log(data, log_time=log_time)
                self.messages_sent += 1


def _address(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
