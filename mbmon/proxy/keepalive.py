"""TCP keepalive on the proxy's sockets, and short words for a connection error.

A peer whose host vanished (power cut, cable pulled) without a FIN or RST is
noticed within about a minute instead of never (an idle client) or at the next
request's timeout (an idle upstream).
"""

from __future__ import annotations

import socket
from typing import Any

__all__ = [
    "KEEPALIVE_COUNT",
    "KEEPALIVE_IDLE",
    "KEEPALIVE_INTERVAL",
    "connection_error",
    "keepalive",
]

#: TCP keepalive on every client and upstream socket: probes after this many idle
#: seconds, every ``KEEPALIVE_INTERVAL`` s, ``KEEPALIVE_COUNT`` unanswered ones close
#: the connection. A peer whose host vanished (power cut, cable pulled) without a
#: FIN or RST is noticed within about a minute instead of never (an idle client)
#: or at the next request's timeout (an idle upstream).
KEEPALIVE_IDLE = 30
KEEPALIVE_INTERVAL = 10
KEEPALIVE_COUNT = 3


def keepalive(sock: Any) -> None:
    """Turn TCP keepalive on for ``sock`` (see :data:`KEEPALIVE_IDLE`); where the
    platform lacks the per-socket timings, its defaults apply."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    except OSError:
        return
    for name, value in (
        ("TCP_KEEPIDLE", KEEPALIVE_IDLE),
        ("TCP_KEEPINTVL", KEEPALIVE_INTERVAL),
        ("TCP_KEEPCNT", KEEPALIVE_COUNT),
    ):
        option = getattr(socket, name, None)
        if option is not None:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, option, value)
            except OSError:
                pass


def connection_error(exc: BaseException | None) -> str:
    """Short words for a connection error."""
    if exc is None:
        return ""
    if isinstance(exc, TimeoutError):
        return "connect timed out"
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused"
    if isinstance(exc, ConnectionResetError):
        return "connection reset"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__
