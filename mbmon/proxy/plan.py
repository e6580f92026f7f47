"""What one proxy run is asked to be, checked: :class:`ProxyPlan` turns the command's
options (addresses already parsed) into the engine's :class:`~mbmon.proxy.config.ProxyConfig`,
the serial sides' factories and the texts the command prints (start-up line,
source name, why it could not start). The command (``mbmon proxy``) stays wiring:
options in, a plan, the hub and its listeners, the engine, one exit status.

No argparse and no printing here: a bad option is a :class:`PlanError` the command
turns into its usage error.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from mbmon.proxy.config import OBSERVE_PRIORITY_ENV, ProxyConfig, endpoint
from mbmon.proxy.guard import ClientFilter, Guard, GuardSpecError

__all__ = ["DEFAULT_LISTEN", "PlanError", "ProxyPlan"]

#: Where clients connect unless ``--listen`` says otherwise: loopback only.
DEFAULT_LISTEN = ("127.0.0.1", 1502)


class PlanError(ValueError):
    """Options that cannot make a proxy run (the message says which and why)."""


@dataclass
class ProxyPlan:
    """One run: the engine's config, the serial ports (``None``: TCP) and their line
    settings, and the names the run is known by."""

    config: ProxyConfig
    upstream_serial: str | None = None
    listen_serial: str | None = None
    settings: Any = None  # mbmon.sources.serial.SerialSettings, when a side is serial
    factories: dict[str, Callable[[Any], Any]] = field(default_factory=dict)

    @classmethod
    def from_options(
        cls,
        args: Any,
        upstream: tuple[str, int] | None,
        listen: tuple[str, int] | None,
    ) -> ProxyPlan:
        """The plan for the parsed options ``args`` of ``mbmon proxy``; ``upstream`` and
        ``listen`` are ``--upstream`` and ``--listen`` parsed (``None``: not given).
        Raises :class:`PlanError` for options that contradict or a bad guard spec."""
        check_options(args)
        try:
            guard = Guard.from_options(
                args.read_only,
                args.allow_write,
                args.deny_write,
                args.guard_exception,
                allow_fc=args.allow_fc,
            )
            clients = ClientFilter(args.allow_from)
        except GuardSpecError as exc:
            raise PlanError(str(exc)) from None
        up_host, up_port = upstream if upstream is not None else ("", 0)
        listen_host, listen_port = listen if listen is not None else DEFAULT_LISTEN
        config = ProxyConfig(
            upstream_host=up_host,
            upstream_port=up_port,
            listen_host=listen_host,
            listen_port=listen_port,
            timeout=args.timeout,
            share_upstream=args.share_upstream or args.upstream_serial is not None,
            upstream_name=args.upstream_serial,
            guard=guard,
            clients=clients,
        )
        plan = cls(config, args.upstream_serial, args.listen_serial)
        # the observing process yields to the forwarding, unless asked not to
        keep = os.environ.get(OBSERVE_PRIORITY_ENV, "").strip().lower() == "normal"
        config.observe_idle = plan.process and not keep
        if plan.serial:
            plan._plug_serial(args.baud, args.parity, args.stopbits)
        return plan

    def _plug_serial(self, baud: int, parity: str, stopbits: int) -> None:
        """The serial sides' factories (:mod:`mbmon.proxy.serial`; pyserial loads when a
        port opens)."""
        from mbmon.proxy.serial import rtu_front, rtu_upstream
        from mbmon.sources.serial import SerialSettings

        self.settings = settings = SerialSettings(baud, parity, stopbits)
        if self.upstream_serial is not None:
            self.factories["upstream"] = rtu_upstream(self.upstream_serial, settings)
        if self.listen_serial is not None:
            self.factories["front"] = rtu_front(self.listen_serial, settings)

    @property
    def serial(self) -> bool:
        """Whether a side is a serial port (the engine then runs in a thread)."""
        return self.upstream_serial is not None or self.listen_serial is not None

    @property
    def process(self) -> bool:
        """Whether the engine forwards in a process of its own: a TCP proxy on POSIX
        (its own GIL: observation never takes CPU time from forwarding; the serial
        variants are bound by the bus; the child's pipes need POSIX)."""
        return not self.serial and os.name == "posix"

    @property
    def upstream(self) -> str:
        """The upstream's name: ``HOST:PORT`` or its serial port."""
        return self.config.upstream

    @property
    def listen(self) -> str:
        """Where clients connect, as asked: ``HOST:PORT`` or the master's serial port."""
        if self.listen_serial is not None:
            return self.listen_serial
        return endpoint(self.config.listen_host, self.config.listen_port)

    def source(self) -> str:
        """The run's source, as the logs name it."""
        return f"proxy {self.listen} -> {self.upstream}"

    def mode(self) -> str:
        """How clients reach the upstream, in words."""
        if self.upstream_serial is not None:
            return f"RTU slave bus {self.settings.text()}, one request at a time"
        if self.config.share_upstream:
            return "shared upstream connection"
        return "one upstream connection per client"

    def startup_line(self, address: tuple[str, int]) -> str:
        """The start-up line (what a supervisor waits for): where, to where, how."""
        if self.listen_serial is not None:
            where = f"{self.listen_serial} (RTU master side, {self.settings.text()})"
        else:
            where = endpoint(*address)
        cfg = self.config
        return (
            f"listening on {where} -> upstream {self.upstream} "
            f"({self.mode()}, timeout {cfg.timeout:g} s, guard {cfg.guard.describe()})"
        )

    def start_error(self, exc: OSError, listen_error: Callable[..., str]) -> str:
        """Why the engine could not start: a serial port that does not open says so
        itself; else ``listen_error`` words the listening socket's failure."""
        if self.serial:
            from mbmon.proxy.serial_line import SerialOpenError

            if isinstance(exc, SerialOpenError):
                return exc.strerror or str(exc)
        cfg = self.config
        return str(listen_error(self.listen, exc, cfg.listen_port))


def check_options(args: Any) -> None:
    """Options of ``mbmon proxy`` that contradict each other: :class:`PlanError`."""
    if (args.upstream is None) == (args.upstream_serial is None):
        raise PlanError("give the upstream once: --upstream HOST:PORT or --upstream-serial PORT")
    if args.listen is not None and args.listen_serial is not None:
        raise PlanError("listen either on --listen ADDR:PORT or on --listen-serial PORT")
    if args.allow_from and args.listen_serial is not None:
        raise PlanError("--allow-from is for TCP clients, not --listen-serial")
    if args.trigger is not None:
        raise PlanError("--trigger works with read and sniff; the proxy logs everything")
