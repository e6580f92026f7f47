"""When the proxy's observing process yields the CPU to the forwarding chain.

What this module owns: putting the observing process (``mbmon proxy``'s parent,
once its forwarding child runs) at idle CPU priority (:func:`observe_idle`), and
bringing it back to normal priority while it is far behind or stopping, where the
system allows (:class:`Catchup`). The pipe's reader in :mod:`mbmon.proxy.remote`
tells :class:`Catchup` of each read; docs/proxy.md says what users see.
"""

from __future__ import annotations

import os
import threading

__all__ = ["Catchup", "observe_idle"]


def observe_idle() -> str | None:
    """Run the calling thread, and every thread it starts from now on, only on CPU time
    the rest of the machine leaves (the observing process, once its forwarding child
    runs): Linux ``SCHED_IDLE``, else nice 19. What was set (``"idle"``, ``"nice 19"``),
    or ``None`` when the system refused both.

    Forwarding and observation share the cores with the clients and the upstream;
    observing at the same priority, the observer's wake-ups took a core from the
    forwarding chain in bursts (a 10 ms batch of records, a 1 MiB chunk compressed),
    and with ``-w x.mcap`` the chain lost a tenth of its throughput while the
    machine idled more (docs/performance.md, "Proxy: the observer yields"). An idle
    thread never delays a runnable forwarding task: the kernel preempts it at once
    and counts its core as free when it places a woken one. The observation stays
    lossless while the machine has idle time, and bounded when it has none: past
    ``max_backlog`` items the child forwards without a copy, counted and reported.
    An unprivileged thread cannot come back from either, so this is for a process
    that only observes (``mbmon proxy``: :attr:`ProxyConfig.observe_idle`);
    where the system allows it, :class:`Catchup` brings the process back to normal
    priority while it is far behind and once it is stopping."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))  # the calling thread
        return "idle"
    except (AttributeError, OSError):
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, 0, 19)
        return "nice 19"
    except (AttributeError, OSError):
        return None


#: A read of this share of the observation pipe finds the observing process behind
#: (a quarter of the 1 MiB pipe: about 6,000 chunk records, a tenth of a second at
#: 8 clients flat out) ...
BEHIND_PIPE_SHARE = 4
#: ... and so does a hub this share of ``max_backlog`` items behind the reader.
BEHIND_SHARE = 8
#: Reads of at most this share of the pipe, with the hub at most a tenth of that
#: behind, this many in a row (about one a handover, 10 ms), find it caught up.
CAUGHT_UP_PIPE_SHARE = 32
CAUGHT_UP_READS = 100


class Catchup:
    """The idle observing process back at normal priority while it is far behind.

    The pipe's reader calls :meth:`read` with the size of each read and the hub's
    backlog (items handed over, not yet taken): a read of ``pipe_size /``
    :data:`BEHIND_PIPE_SHARE` bytes or more, or a hub more than ``max_backlog /
    BEHIND_SHARE`` items behind, puts every thread of the process back to
    ``SCHED_OTHER``, so the observation catches up instead of falling past its
    backlog on a machine with no idle time;
    :data:`CAUGHT_UP_READS` small reads in a row with a small backlog put them back
    to ``SCHED_IDLE``. Leaving ``SCHED_IDLE`` needs the privilege to (root,
    ``CAP_SYS_NICE`` or an ``RLIMIT_NICE`` of 20): without it the first attempt
    fails and the process stays idle (:attr:`able` is then False).
    """

    def __init__(self, max_backlog: int, pipe_size: int) -> None:
        self.behind_items = max(1, max_backlog // BEHIND_SHARE)
        self.behind_bytes = pipe_size // BEHIND_PIPE_SHARE
        self.caught_up_bytes = pipe_size // CAUGHT_UP_PIPE_SHARE
        self.idle = True
        self.able = True
        self.returns = 0  # times it went back to normal priority
        self._calm = 0

    def stop(self) -> None:
        """The run is ending: normal priority from now on, where allowed, so that the
        last observations, the log's last chunks and the summary do not wait for idle
        time on a busy machine (a Ctrl-C took over 25 s at load 17 without this)."""
        if self.able and self.idle:
            self.idle = not _set_policy(os.SCHED_OTHER)
        self.able = False

    def read(self, n: int, backlog: int) -> None:
        """One read of ``n`` bytes, the hub ``backlog`` items behind after it."""
        if not self.able:
            return
        if self.idle:
            if n >= self.behind_bytes or backlog >= self.behind_items:
                if _set_policy(os.SCHED_OTHER):
                    self.idle = False
                    self.returns += 1
                    self._calm = 0
                else:
                    self.able = False
            return
        if n >= self.caught_up_bytes or backlog * 10 >= self.behind_items:
            self._calm = 0
            return
        self._calm += 1
        if self._calm >= CAUGHT_UP_READS:
            self.idle = _set_policy(os.SCHED_IDLE) or self.idle


def _set_policy(policy: int) -> bool:
    """Every thread of this process to ``policy``; False when the system refuses."""
    for thread in threading.enumerate():
        tid = thread.native_id
        if tid is None:
            continue
        try:
            os.sched_setscheduler(tid, policy, os.sched_param(0))
        except ProcessLookupError:  # ended meanwhile
            continue
        except OSError:
            return False
    return True
