"""The proxy's settings and counters: :class:`ProxyConfig` (where to listen, where
to forward, the rules), :class:`ProxyStats` (the run's counters and its closing
summary), the gateway exception codes and :func:`endpoint` (an endpoint's text).

Plain data: nothing here touches a socket or a loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from mbmon.proxy.guard import ClientFilter, Guard

__all__ = [
    "GATEWAY_PATH_UNAVAILABLE",
    "GATEWAY_TARGET_FAILED",
    "HANDOVER",
    "MAX_BACKLOG",
    "OBSERVE_PRIORITY_ENV",
    "ProxyConfig",
    "ProxyStats",
    "endpoint",
]

GATEWAY_PATH_UNAVAILABLE = 0x0A
GATEWAY_TARGET_FAILED = 0x0B

#: How far (chunks and events) the hub may fall behind before chunks are forwarded
#: without a copy: bounds the queue's memory (about 250 bytes an item).
MAX_BACKLOG = 50_000

#: Seconds observations wait to go to the hub together (:attr:`ProxyConfig.handover`).
HANDOVER = 0.01

#: The environment variable that keeps ``mbmon proxy``'s observing process at the
#: priority it was started with (``normal``) instead of idle
#: (:attr:`ProxyConfig.observe_idle`).
OBSERVE_PRIORITY_ENV = "MBMON_OBSERVE_PRIORITY"


def endpoint(host: str, port: int) -> str:
    """``HOST:PORT``, IPv6 as ``[ADDR]:PORT`` (the model's endpoint text)."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


@dataclass
class ProxyConfig:
    """Where to listen, where to forward, and the rules (see the module text)."""

    upstream_host: str
    upstream_port: int
    listen_host: str = "127.0.0.1"
    listen_port: int = 1502
    timeout: float = 3.0
    share_upstream: bool = False
    guard: Guard = field(default_factory=Guard)
    clients: ClientFilter = field(default_factory=ClientFilter)
    backoff_min: float = 0.05
    backoff_max: float = 1.0
    max_backlog: int = MAX_BACKLOG
    #: how long observations wait to be handed to the hub in one batch (0: once per
    #: loop iteration). 10 ms: the hub's thread wakes (and takes the GIL from the
    #: forwarding) a hundred times a second instead of twice per request, which at
    #: one client cuts the hub's CPU per request by half or more; with the engine in
    #: a child process every batch is a pipe write and wakes the observing process's
    #: reader and hub threads, whose per-batch work at 8 clients cost over a
    #: microsecond a request at 2 ms (docs/performance.md)
    handover: float = HANDOVER
    #: the upstream's name when it is not a TCP server (an RTU bus: its serial port)
    upstream_name: str | None = None
    #: with the engine in a child process: the observing process (the one that starts
    #: it) runs at the lowest CPU priority from then on (Linux ``SCHED_IDLE``; nice 19
    #: elsewhere), so the forwarding never waits for it (``mbmon proxy`` sets it unless
    #: ``MBMON_OBSERVE_PRIORITY=normal``; off by default, as it lowers the calling
    #: thread's priority for good)
    observe_idle: bool = False

    @property
    def upstream(self) -> str:
        if self.upstream_name is not None:
            return self.upstream_name
        return endpoint(self.upstream_host, self.upstream_port)


@dataclass
class ProxyStats:
    """Counters of a run, for the summary on exit (written by the engine's thread)."""

    clients: int = 0
    clients_refused: int = 0
    clients_dropped: int = 0
    requests: int = 0
    responses: int = 0
    exceptions_0a: int = 0
    exceptions_0b: int = 0
    guard_refusals: int = 0
    late_dropped: int = 0
    unanswered: int = 0  # RTU master requests left silent (gateway 0x0A/0x0B)
    unmatched_dropped: int = 0
    unmatched_forwarded: int = 0  # per client: answers with an unknown tid, forwarded
    upstream_renewed: int = 0  # per client: connections renewed after a gateway timeout
    upstream_connects: int = 0
    upstream_failures: int = 0
    bytes_from_clients: int = 0
    bytes_to_clients: int = 0
    not_observed: int = 0

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def summary(self) -> str:
        """The one-paragraph summary printed on exit."""
        made = self.exceptions_0a + self.exceptions_0b + self.guard_refusals
        lines = [
            f"clients {self.clients} (refused {self.clients_refused}, "
            f"dropped {self.clients_dropped})",
            f"requests {self.requests}, responses {self.responses}",
            f"exceptions made by the proxy {made} (0x0A {self.exceptions_0a}, "
            f"0x0B {self.exceptions_0b}, guard {self.guard_refusals})",
            f"guard refusals {self.guard_refusals}, late answers dropped {self.late_dropped}, "
            f"unmatched answers dropped {self.unmatched_dropped}, "
            f"forwarded with an unknown tid {self.unmatched_forwarded}",
            f"upstream connections {self.upstream_connects} "
            f"(failed attempts {self.upstream_failures}, "
            f"renewed after a gateway timeout {self.upstream_renewed})",
            f"bytes client->server {self.bytes_from_clients}, "
            f"server->client {self.bytes_to_clients}",
        ]
        if self.unanswered:
            lines.append(
                f"RTU master requests left unanswered (silence for 0x0A/0x0B) {self.unanswered}"
            )
        if self.not_observed:
            lines.append(f"chunks forwarded but not observed (monitor behind) {self.not_observed}")
        return "\n".join(lines)
