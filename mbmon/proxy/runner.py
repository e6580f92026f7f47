"""Running the engine: :class:`ProxyThread` (its own asyncio loop in its own thread)
and :func:`attach_engine`, the one way a command runs a proxy, in a thread or in
a child process (:class:`~mbmon.proxy.remote.ProxyProcess`), wired to a hub;
:func:`unresolved` tells at start-up whether the upstream's host resolves.
"""

from __future__ import annotations

import asyncio
import sys
import threading
from collections.abc import Callable
from typing import Any

from mbmon.proxy.config import ProxyConfig
from mbmon.proxy.engine import ProxyEngine
from mbmon.proxy.observer import Observer

__all__ = ["SWITCH_INTERVAL", "ProxyThread", "attach_engine", "unresolved"]

#: The interpreter's thread switch interval while a threaded proxy runs (default 5 ms).
SWITCH_INTERVAL = 0.0002


class ProxyThread:
    """Runs a :class:`ProxyEngine` on its own asyncio loop in its own thread.

    :meth:`start` returns once the listening socket is bound (or raises the
    ``OSError`` that prevented it); :meth:`stop` is safe from any thread and
    from signal handlers; ``on_exit`` runs in the engine's thread when the loop
    has ended (the command stops the hub there).
    """

    def __init__(self, engine: ProxyEngine, on_exit: Callable[[], None] | None = None) -> None:
        self.engine = engine
        self._on_exit = on_exit
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=self._main, name="mbmon-proxy", daemon=True)

    def start(self) -> tuple[str, int]:
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise self._error
        assert self.engine.address is not None
        return self.engine.address

    def _main(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            try:
                loop.run_until_complete(self.engine.start())
            except BaseException as exc:
                self._error = exc
                return
            finally:
                self._ready.set()
            loop.run_until_complete(self.engine.serve())
        finally:
            try:
                for task in asyncio.all_tasks(loop):
                    task.cancel()
                loop.run_until_complete(asyncio.sleep(0))
                loop.close()
            finally:
                self.engine.observer.flush()
                if self._on_exit is not None:
                    self._on_exit()

    def stop(self) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self.engine.request_stop)
            except RuntimeError:  # closed in between
                pass

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the thread; whether it has ended."""
        self._thread.join(timeout)
        return not self._thread.is_alive()


def unresolved(host: str, port: int, wait: float = 2.0) -> str | None:
    """Why ``host`` does not resolve (``None`` when it does, or is an address): the
    lookup runs in a thread, so a slow resolver delays the start by ``wait`` at most."""
    import ipaddress
    import socket

    try:
        ipaddress.ip_address(host.split("%", 1)[0])
        return None
    except ValueError:
        pass
    result: list[str | None] = []

    def lookup() -> None:
        try:
            socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
            result.append(None)
        except (OSError, UnicodeError) as exc:
            result.append(getattr(exc, "strerror", None) or str(exc) or type(exc).__name__)

    thread = threading.Thread(target=lookup, name="mbmon-resolve", daemon=True)
    thread.start()
    thread.join(wait)
    if not result:
        return f"no answer from the resolver in {wait:g} s"
    return result[0]


def attach_engine(
    hub: Any, config: ProxyConfig, *, process: bool = False, stage: Any = None, **factories: Any
) -> tuple[Any, Any, Any]:
    """A :class:`~mbmon.proxy.engine.ProxyEngine` for ``config`` wired to ``hub``: the
    one way a command runs a proxy (``proxy``, ``demo``).

    Its observations go to the hub's queue in batches (the hub's count of what it
    has taken, :attr:`~mbmon.hub.Hub.seen`, bounds the backlog), and its
    :class:`ProxyThread` stops the hub when the engine's loop
    ends. Returns ``(engine, thread, observer)``;
    ``thread.start()`` binds the listening socket. ``factories`` (``upstream=``,
    ``front=``) plug in the serial variants (:mod:`mbmon.proxy.serial`).

    ``process``: the engine runs in a child process instead of a thread
    (:class:`~mbmon.proxy.remote.ProxyProcess`, the same calls; no factories);
    ``engine`` is then a :class:`~mbmon.proxy.remote.RemoteEngine` and ``observer``
    the process (its ``skipped``); ``stage`` (a child process only): the compiled
    core's stage its observations go to (:class:`~mbmon.core.chunks.ChunkCore`).
    """
    if process:
        if factories:
            raise ValueError("the serial variants run the engine in a thread")
        from mbmon.proxy.remote import ProxyProcess

        proc = ProxyProcess(config, hub, on_exit=hub.stop, stage=stage)
        return proc.engine, proc, proc

    if stage is not None:
        raise ValueError("the compiled core observes an engine in a child process only")
    observer = Observer(hub.put, hub.new_stream, meter=hub, max_backlog=config.max_backlog)
    engine = ProxyEngine(config, observer, submit=hub.submit, **factories)
    # The engine's thread must get the GIL back quickly when a packet arrives while
    # the hub's thread decodes and writes: the default 5 ms switch interval would add
    # up to 5 ms to a forwarded answer whenever the hub is busy.
    sys.setswitchinterval(SWITCH_INTERVAL)
    thread = ProxyThread(engine, on_exit=hub.stop)
    return engine, thread, observer
