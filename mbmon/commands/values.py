"""The argparse value types every command shares (ports, endpoints, counts, times
as numbers). A bad value is an ``argparse.ArgumentTypeError`` (argparse prints it
with the usage, exit 2), or a :class:`~mbmon.commands.ending.UsageError` for values
checked after parsing. Re-exported by :mod:`mbmon.commands.options` and
:mod:`mbmon.commands.common`.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from mbmon.commands.ending import UsageError


def whole_number(what: str, lowest: int, highest: int, noun: str = "") -> Callable[[str], int]:
    """An argparse type for a whole number ``lowest..highest`` (decimal or ``0x``):
    the one home of integer option checks. Errors say "not a {noun or what}" and
    "{what} out of range"."""

    def parse(text: str) -> int:
        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a {noun or what}: {text!r}") from None
        if not lowest <= value <= highest:
            raise argparse.ArgumentTypeError(f"{what} out of range {lowest}..{highest}: {value}")
        return value

    parse.__name__ = what  # argparse names the type in some messages
    return parse


#: A TCP/UDP port 1..65535.
port = whole_number("port", 1, 65535, "port number")
#: A Modbus unit id of a server (1..247).
unit_id = whole_number("unit id", 1, 247)
#: A Modbus exception code mbmon answers with.
exception_code = whole_number("exception code", 1, 255)


def positive(text: str) -> float:
    """An argparse type: a number > 0 (seconds, speeds)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0 or value != value or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0: {text}")
    return value


def positive_int(text: str) -> int:
    """An argparse type: a whole number > 0 (baud rates, counts)."""
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {value}")
    return value


def endpoint(text: str) -> str:
    """An argparse type: ``HOST``, ``HOST:PORT``, ``[IPv6]:PORT`` or a serial device name."""
    value = text.strip()
    if not value or any(c.isspace() for c in value):
        raise argparse.ArgumentTypeError(f"not an endpoint: {text!r} (use HOST or HOST:PORT)")
    if value.startswith("/"):
        return value  # an RTU bus (serial device or dump file name)
    if value.startswith("["):
        close = value.find("]")
        if close < 0 or (close + 1 < len(value) and value[close + 1] != ":"):
            raise argparse.ArgumentTypeError(f"not an endpoint: {text!r} (use [ADDR]:PORT)")
        rest = value[close + 2 :] if close + 1 < len(value) else ""
    elif value.count(":") == 1:
        host, _, rest = value.partition(":")
        if not host:
            raise argparse.ArgumentTypeError(f"not an endpoint: {text!r} (no host)")
    else:
        rest = ""
    if rest:
        port(rest)  # raises with a clear message
    return value


def split_host_port(
    text: str, *, default_host: str | None = None, lowest: int = 1
) -> tuple[str, int]:
    """The one parser of socket addresses given on the command line: ``HOST:PORT``,
    ``[IPv6]:PORT``, or a bare ``PORT`` when ``default_host`` is given (listen
    addresses: loopback). ``lowest`` is 0 where port 0 (any free port) makes sense.
    Raises ``ValueError`` with the reason."""
    value = text.strip()
    host: str
    if value.startswith("["):
        host, sep, port_text = value[1:].partition("]:")
        if not sep:
            raise ValueError("use [ADDR]:PORT for IPv6")
    elif ":" in value:
        host, _, port_text = value.rpartition(":")
    elif default_host is not None:
        host, port_text = default_host, value
    else:
        raise ValueError("use HOST:PORT")
    if not host:
        if default_host is None:
            raise ValueError("the host is missing")
        host = default_host
    if any(c.isspace() for c in host):
        raise ValueError("not a host name")
    try:
        number = int(port_text, 10)
    except ValueError:
        raise ValueError("not a port number") from None
    if not lowest <= number <= 65535:
        raise ValueError(f"port out of range {lowest}..65535")
    return host, number


def parse_address(
    text: str, what: str, *, default_host: str | None = None, lowest: int = 1
) -> tuple[str, int]:
    """:func:`split_host_port` for an option checked after parsing: a bad address is
    a :class:`UsageError` naming the option (``--upstream 'x': use HOST:PORT``)."""
    try:
        return split_host_port(text, default_host=default_host, lowest=lowest)
    except ValueError as exc:
        raise UsageError(f"{what} {text.strip()!r}: {exc}") from None


def listen_address(text: str) -> tuple[str, int]:
    """An argparse type for where a server of mbmon listens: ``[HOST:]PORT``, a bare
    PORT on 127.0.0.1, port 0 for a free one."""
    try:
        return split_host_port(text, default_host="127.0.0.1", lowest=0)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: {exc}") from None
