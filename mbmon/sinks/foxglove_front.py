"""The front door of the live Foxglove feed: every Foxglove client gets in, whatever
name of the protocol it offers.

foxglove-sdk's server accepts only clients that offer the WebSocket subprotocol
``foxglove.sdk.v1`` and refuses the others with HTTP 400. Older Foxglove and
Lichtblick releases offer only ``foxglove.websocket.v1``: the same protocol
under its former name (identical messages, byte for byte). The feed's server
therefore listens on a loopback port of its own, and :class:`SubprotocolFront`
listens where the user asked (``--foxglove [HOST:]PORT``) and relays each
connection to it. For a client that offers only the former name it rewrites
the one header of the opening handshake that names the subprotocol, in the
request (to ``foxglove.sdk.v1``) and in the answer (back to the name the client
offered); after the handshake both ways are copied byte for byte. A client
that offers ``foxglove.sdk.v1`` goes through untouched.

:func:`rewrite_request` and :func:`rewrite_response` own the header rewrite
(pure, tested as byte tables); the relay runs an asyncio loop in a daemon
thread of its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
_HEADER = b"sec-websocket-protocol"
_END = b"\r\n\r\n"
#: the longest opening handshake read (a browser's is well under 4 KiB)
HANDSHAKE_LIMIT = 1 << 16
_COPY = 1 << 16


def _offered(value: bytes) -> list[str]:
    return [t.strip() for t in value.decode("latin-1").split(",") if t.strip()]


def rewrite_request(head: bytes) -> tuple[bytes, bool]:
    """The opening handshake request ``head`` (up to and including the blank line) as
    the SDK accepts it, and whether it was rewritten: a request that offers
    ``foxglove.websocket.v1`` and not ``foxglove.sdk.v1`` offers the latter instead;
    any other request is returned as it is."""
    lines = head.split(b"\r\n")
    found: list[int] = []
    offered: list[str] = []
    for n, line in enumerate(lines[1:], 1):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == _HEADER:
            found.append(n)
            offered += _offered(value)
    if SDK_SUBPROTOCOL in offered or LEGACY_SUBPROTOCOL not in offered:
        return head, False
    first = found[0]
    lines[first] = b"Sec-WebSocket-Protocol: " + SDK_SUBPROTOCOL.encode()
    for n in reversed(found[1:]):
        del lines[n]
    return b"\r\n".join(lines), True


def rewrite_response(head: bytes) -> bytes:
    """The SDK's handshake answer ``head`` for a client that offered only
    ``foxglove.websocket.v1``: the subprotocol it accepted named as the client knows it."""
    lines = head.split(b"\r\n")
    for n, line in enumerate(lines[1:], 1):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == _HEADER and _offered(value) == [SDK_SUBPROTOCOL]:
            lines[n] = b"Sec-WebSocket-Protocol: " + LEGACY_SUBPROTOCOL.encode()
    return b"\r\n".join(lines)


def listening_socket(host: str, port: int) -> socket.socket:
    """A TCP socket listening on ``host:port`` (a name, IPv4 or IPv6; port 0: a free
    one). Raises :class:`OSError` (in use, no such address, not permitted)."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    if not infos:  # pragma: no cover - getaddrinfo raises rather than answer nothing
        raise OSError(f"no address for {host}")
    family, _type, _proto, _name, address = infos[0]
    return socket.create_server(address[:2], family=family)


class SubprotocolFront:
    """Listen on ``host:port`` and relay every connection to ``127.0.0.1:upstream_port``
    (the SDK's server), rewriting the handshake of clients that offer only
    ``foxglove.websocket.v1`` (see the module text). The socket is bound before the
    constructor returns (an :class:`OSError` when it cannot be); :attr:`port` is
    the port bound. :meth:`close` stops listening and ends every relayed connection."""

    def __init__(self, host: str, port: int, upstream_port: int) -> None:
        self._sock = listening_socket(host, port)
        self.port: int = int(self._sock.getsockname()[1])
        self._upstream_port = upstream_port
        self._loop = asyncio.new_event_loop()
        self._writers: set[asyncio.StreamWriter] = set()
        self._server: asyncio.Server | None = None
        ready = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(ready,), name="mbmon-foxglove-front", daemon=True
        )
        self._thread.start()
        ready.wait(10)
        #: connections whose handshake was rewritten (clients offering only the old name)
        self.rewritten = 0

    def _run(self, ready: threading.Event) -> None:
        loop = self._loop
        asyncio.set_event_loop(loop)

        async def start() -> None:
            self._server = await asyncio.start_server(
                self._relay, sock=self._sock, limit=HANDSHAKE_LIMIT
            )

        try:
            loop.run_until_complete(start())
        finally:
            ready.set()
        try:
            loop.run_forever()
        finally:
            loop.close()

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """One client: its handshake (rewritten if need be), then bytes both ways."""
        self._writers.add(writer)
        up_writer: asyncio.StreamWriter | None = None
        try:
            try:
                head = await reader.readuntil(_END)
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError):
                return
            head, legacy = rewrite_request(head)
            up_reader, up_writer = await asyncio.open_connection(
                "127.0.0.1", self._upstream_port, limit=HANDSHAKE_LIMIT
            )
            self._writers.add(up_writer)
            up_writer.write(head)
            if legacy:
                self.rewritten += 1
                try:
                    answer = await up_reader.readuntil(_END)
                except (asyncio.IncompleteReadError, asyncio.LimitOverrunError) as exc:
                    partial = getattr(exc, "partial", b"")
                    writer.write(partial)
                    return
                writer.write(rewrite_response(answer))
            await asyncio.gather(_copy(reader, up_writer), _copy(up_reader, writer))
        except OSError:
            return
        finally:
            for w in (writer, up_writer):
                if w is not None:
                    self._writers.discard(w)
                    w.close()

    def close(self) -> None:
        """Stop listening, end every relayed connection and the relay's thread. Idempotent."""
        loop = self._loop
        if loop.is_closed() or not self._thread.is_alive():
            with contextlib.suppress(OSError):
                self._sock.close()
            return

        async def stop() -> None:
            if self._server is not None:
                self._server.close()
            for w in list(self._writers):
                w.close()
            tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            loop.stop()

        asyncio.run_coroutine_threadsafe(stop(), loop)
        self._thread.join(5)
        with contextlib.suppress(OSError):
            self._sock.close()


async def _copy(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    """Bytes from ``src`` to ``dst`` as they come, until either side ends; then ``dst``
    is closed, which ends the other direction too."""
    try:
        while data := await src.read(_COPY):
            dst.write(data)
            await dst.drain()
    except OSError:
        pass
    finally:
        dst.close()
