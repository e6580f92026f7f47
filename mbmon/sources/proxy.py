"""The proxy as a live source of the hub: what it forwards, observed.

:class:`ProxySource` implements the source contract (:mod:`mbmon.sources.base`)
over the proxy's public API (:mod:`mbmon.proxy`): the forwarding engine runs in a
thread of its own (:class:`~mbmon.proxy.runner.ProxyThread`, with the serial
variants' factories) or in a child process
(:class:`~mbmon.proxy.remote.ProxyProcess`: its own GIL, observation never takes
CPU time from forwarding), and its observations reach the hub's thread-safe
queue in batches. The proxy forwards first and observes second: nothing here can
stall or alter traffic. When the engine's loop ends, the hub is stopped.

:meth:`ProxySource.open` binds the listening socket (or opens the serial port),
so a proxy that cannot listen fails before any log is opened:
:class:`ProxyStartError` carries the system's error for the command's words.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from mbmon.model import Event
from mbmon.proxy.runner import attach_engine
from mbmon.sources.base import BaseSource, SourceError, SourceMode

if TYPE_CHECKING:
    from mbmon.hub import Hub

__all__ = ["CoreOutput", "ProxySource", "ProxyStartError"]


class ProxyStartError(SourceError):
    """The proxy cannot listen (or open its serial port): the system's ``error``."""

    def __init__(self, error: OSError) -> None:
        super().__init__(error.strerror or str(error))
        self.error = error


class ProxySource(BaseSource):
    """The traffic a proxy forwards for ``config`` (a :class:`~mbmon.proxy.config.ProxyConfig`).

    ``process=True`` runs the engine in a child process (TCP only, POSIX);
    ``factories`` (``upstream=``, ``front=``) plug in the serial variants, which
    run in a thread. After :meth:`open`: :attr:`engine` (its ``stats`` and
    ``figures()``), :attr:`runner` (the thread or process) and :attr:`address`
    (where it listens).
    """

    mode: SourceMode = "live"

    def __init__(
        self,
        config: Any,
        *,
        process: bool = False,
        factories: dict[str, Any] | None = None,
        name: str = "proxy",
        core: CoreOutput | None = None,
    ) -> None:
        super().__init__()
        if process and factories:
            raise ValueError("the serial variants run the engine in a thread")
        self.config = config
        self.process = process
        self.factories = dict(factories or {})
        self.name = name
        self.engine: Any = None
        self.runner: Any = None
        self.observer: Any = None
        self.address: tuple[str, int] | None = None
        #: with ``core`` (a child process only): how the compiled core writes the lines
        self.core = core
        #: its stage (:class:`~mbmon.core.chunks.ChunkCore`) once open
        self.live: Any = None
        self._hub: Any = None

    def open(self, hub: Hub) -> None:
        """Make the engine, wire its observations to ``hub`` and start it: it listens
        when this returns (:class:`ProxyStartError` when it cannot)."""
        super().open(hub)
        if self.core is not None:
            self.live = self.core.stage(hub)
            hub.add_ticker(self.live)
        self.engine, self.runner, self.observer = attach_engine(
            hub, self.config, process=self.process, stage=self.live, **self.factories
        )
        self._hub = hub
        try:
            self.address = self.runner.start()
        except OSError as exc:
            self.runner.stop()
            raise ProxyStartError(exc) from None

    def put_event(self, event: Event) -> None:
        """An event of the command's own (a warning) into the run, from any thread:
        through the core's stage while it observes, else the hub's queue."""
        live = self.live
        if live is None or self._hub is None:
            if self._hub is not None:
                self._hub.put(event)
        else:
            self._hub.submit(lambda: live.event(event))

    def stop(self) -> None:
        """Stop the engine (its last events reach the hub) and wait for it (5 s at most)."""
        if self.runner is not None:
            self.runner.stop()
            self.runner.join(5.0)

    def stats(self) -> dict[str, Any]:
        """The engine's figures for the screen (clients, refusals, upstream state)."""
        return dict(self.engine.figures()) if self.engine is not None else {}

    def closing(self, ts: float) -> list[Event]:
        """Nothing: the engine's own events already closed its streams."""
        return []

    @property
    def ended_unexpectedly(self) -> bool:
        """The forwarding process died: its last counters are all there is."""
        return self.engine is not None and getattr(self.engine, "final", True) is False

    def summary(self) -> list[str]:
        """The engine's counters (what it forwarded, refused, answered itself), with
        the observations the hub could not take counted as not observed."""
        if self.engine is None:
            return []
        stats = self.engine.stats
        stats.not_observed = self.observer.skipped
        lines = list(stats.summary().splitlines())
        if self.live is not None:
            handed = self.live.handed
            lines.append(
                "observed by the compiled core"
                + ("" if handed is None else f", then the Python pipeline ({handed})")
            )
        return lines


@dataclass
class CoreOutput:
    """How the proxy's observation runs on the compiled core (:mod:`mbmon.core.chunks`):
    the view and JSON choice of its lines, the pairing timeout, and ``write``/``flush``
    of stdout's bytes (``None`` with ``-q``)."""

    view: Any
    as_json: bool
    timeout: float
    write: Callable[[bytes], Any] | None  # None: -q (lines made, dropped)
    flush: Callable[[], Any] | None

    def stage(self, hub: Hub) -> Any:
        """The core's hub stage, ``hub``'s pipeline waiting behind it."""
        from mbmon.core.chunks import ChunkCore

        return ChunkCore(
            timeout=self.timeout,
            view=self.view,
            as_json=self.as_json,
            write=self.write,
            flush=self.flush,
            pipeline=hub.pipeline,
        )
