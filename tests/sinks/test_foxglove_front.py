"""The Foxglove feed's front door: the handshake rewrite as byte tables, and the relay
with a real WebSocket client (``websockets``) in front of a real foxglove-sdk server."""

from __future__ import annotations

import socket

import pytest

from mbmon.sinks.foxglove_front import (
    LEGACY_SUBPROTOCOL,
    SDK_SUBPROTOCOL,
    listening_socket,
    rewrite_request,
    rewrite_response,
)

KEY = b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"


def request(*protocol_lines: bytes) -> bytes:
    return (
        b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUpgrade: websocket\r\n"
        b"Connection: Upgrade\r\n" + KEY + b"".join(line + b"\r\n" for line in protocol_lines)
        + b"Sec-WebSocket-Version: 13\r\n\r\n"
    )  # fmt: skip


@pytest.mark.parametrize(
    ("lines", "expected", "rewritten"),
    [
        # the former name only: offered under the SDK's name
        ([b"Sec-WebSocket-Protocol: foxglove.websocket.v1"],
         [b"Sec-WebSocket-Protocol: foxglove.sdk.v1"], True),
        # any spelling of the header, other names beside it, several header lines
        ([b"sec-websocket-protocol:foxglove.websocket.v1, x.v2"],
         [b"Sec-WebSocket-Protocol: foxglove.sdk.v1"], True),
        ([b"Sec-WebSocket-Protocol: x.v2", b"SEC-WEBSOCKET-PROTOCOL: foxglove.websocket.v1"],
         [b"Sec-WebSocket-Protocol: foxglove.sdk.v1"], True),
        # the SDK's name offered: untouched, whatever else is offered
        ([b"Sec-WebSocket-Protocol: foxglove.websocket.v1, foxglove.sdk.v1"],
         [b"Sec-WebSocket-Protocol: foxglove.websocket.v1, foxglove.sdk.v1"], False),
        ([b"Sec-WebSocket-Protocol: foxglove.sdk.v1"],
         [b"Sec-WebSocket-Protocol: foxglove.sdk.v1"], False),
        # neither: untouched (the SDK refuses it, as it should)
        ([b"Sec-WebSocket-Protocol: foxglove.websocket.v2"],
         [b"Sec-WebSocket-Protocol: foxglove.websocket.v2"], False),
        ([], [], False),
    ],
)  # fmt: skip
def test_rewrite_request(lines: list[bytes], expected: list[bytes], rewritten: bool) -> None:
    assert rewrite_request(request(*lines)) == (request(*expected), rewritten)


def test_rewrite_response() -> None:
    head = (
        b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n"
        b"sec-websocket-protocol: foxglove.sdk.v1\r\n\r\n"
    )
    assert rewrite_response(head) == head.replace(
        b"sec-websocket-protocol: foxglove.sdk.v1",
        b"Sec-WebSocket-Protocol: foxglove.websocket.v1",
    )
    refused = b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n\r\n"
    assert rewrite_response(refused) == refused
    assert (LEGACY_SUBPROTOCOL, SDK_SUBPROTOCOL) == ("foxglove.websocket.v1", "foxglove.sdk.v1")


def test_listening_socket_names_ipv4_ipv6_and_refuses_a_port_in_use() -> None:
    for host in ("127.0.0.1", "localhost", "::1"):
        try:
            sock = listening_socket(host, 0)
        except OSError as exc:  # a host without IPv6 loopback
            assert host == "::1", exc
            continue
        with sock:
            assert sock.getsockname()[1] > 0
            with pytest.raises(OSError, match="in use"):
                listening_socket(host, sock.getsockname()[1])
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        assert s.getsockname()[1] > 0
