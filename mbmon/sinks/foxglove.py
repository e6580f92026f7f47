"""The live Foxglove feed: the MCAP log's topics served over Foxglove's WebSocket protocol.

A hub listener (``--foxglove [HOST:]PORT``): every record becomes the same
messages, on the same topics with the same JSON schemas, as in an MCAP log
(:mod:`mbmon.io.mcap.layout` makes them for both), so Foxglove's Log panel shows
the monitor lines and a Plot panel shows ``/hrss/state.a1`` live, exactly as
when the log is opened later. Served by the ``foxglove-sdk`` package (the
optional extra ``mbmon[foxglove]``); listens on 127.0.0.1 unless told otherwise.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from mbmon.model import Chunk, Event, Record

#: Where the feed listens unless told otherwise (Foxglove's default port, loopback).
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765

Messages = Iterable[tuple[str, int, bytes]]


class FoxgloveError(Exception):
    """The feed cannot start (the package is missing, the port is taken); says why."""


def parse_address(text: str) -> tuple[str, int]:
    """``PORT``, ``HOST:PORT`` or ``[V6]:PORT`` → (host, port); loopback when no host."""
    text = text.strip()
    host, port_text = DEFAULT_HOST, text
    if text.startswith("["):
        close = text.find("]")
        host, port_text = text[1:close], text[close + 2 :]
    elif ":" in text:
        host, _, port_text = text.rpartition(":")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"not a port: {text!r} (use PORT or HOST:PORT)") from None
    if not 0 <= port < 65536:
        raise ValueError(f"port out of range: {port}")
    return host or DEFAULT_HOST, port


class FoxgloveListener:
    """Serves records and raw chunks as Foxglove WebSocket messages while the run lasts.

    ``topics`` maps each topic to ``(schema name, JSON schema bytes)``;
    ``record_messages(record)`` and ``raw_messages(item)`` give the
    ``(topic, log_time_ns, json_bytes)`` messages of a record and of a raw chunk
    or event — the MCAP layout's own functions, so the feed and the log agree.
    Channels are created when the server starts, so a client sees every topic
    at once.
    """

    name = "Foxglove feed"

    def __init__(
        self,
        topics: dict[str, tuple[str, bytes]],
        record_messages: Callable[[Record], Messages],
        raw_messages: Callable[[Chunk | Event], Messages] | None = None,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        server_name: str = "mbmon",
    ) -> None:
        try:
            import foxglove
        except ImportError:
            raise FoxgloveError(
                "the live Foxglove feed needs the foxglove-sdk package: "
                "pip install 'mbmon[foxglove]'"
            ) from None
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name=server_name, host=host, port=port, context=self._context
            )
        except Exception as exc:  # the SDK raises its own error types
            raise FoxgloveError(f"cannot serve on {host}:{port}: {exc}") from None
        self.host = host
        self._channels: dict[str, Any] = {}
        for topic, (schema_name, schema) in topics.items():
            self._channels[topic] = foxglove.Channel(
                topic,
                schema=foxglove.Schema(name=schema_name, encoding="jsonschema", data=schema),
                message_encoding="json",
                context=self._context,
            )
        self._record_messages = record_messages
        self._raw_messages = raw_messages
        self.sent = 0

    @property
    def port(self) -> int:
        """The port the feed listens on (the real one when 0 was asked for)."""
        return int(self._server.port)

    @property
    def address(self) -> str:
        """``ws://HOST:PORT``, what Foxglove's "Open connection" dialog wants."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def _send(self, messages: Messages) -> None:
        channels = self._channels
        for topic, log_time, data in messages:
            channel = channels.get(topic)
            if channel is not None:
                channel.log(data, log_time=log_time)
                self.sent += 1

    def on_records(self, records: list[Record]) -> None:
        make = self._record_messages
        for record in records:
            self._send(make(record))

    def on_chunk(self, chunk: Chunk) -> None:
        if self._raw_messages is not None:
            self._send(self._raw_messages(chunk))

    def on_event(self, event: Event) -> None:
        if self._raw_messages is not None:
            self._send(self._raw_messages(event))

    def close(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            for channel in self._channels.values():
                channel.close()
            server.stop()
