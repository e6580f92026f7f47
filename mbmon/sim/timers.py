"""The HRSS Timer registers for the simulator: Timer[1..n] count milliseconds while running.

Each timer is two holding registers (low word first, manual Appendix II) that
a client may read or write at any time; the T_STOP command (Table 16) starts
and stops it. A running timer's registers are brought up to date when the
robot steps; a client that writes a running timer sets where it goes on
counting from. Time is an input (``now``, seconds).
"""

from __future__ import annotations

from dataclasses import dataclass

from mbmon.sim.spec import join_i32, split_i32, u16

__all__ = ["TIMER_LIMIT", "Timers"]

TIMER_LIMIT = 999_999_999  # milliseconds either way


@dataclass(slots=True)
class _Timer:
    running: bool = False
    since: float = 0.0
    base_ms: int = 0


class Timers:
    """Timer[1..``count``] in ``holding`` from ``first``, ``stride`` registers apart."""

    def __init__(self, holding: list[int], first: int, stride: int, count: int) -> None:
        self._holding = holding
        self._first, self._stride = first, stride
        self._timers = [_Timer() for _ in range(count + 1)]  # index 1..count

    def __getitem__(self, n: int) -> _Timer:
        return self._timers[n]

    def run(self, n: int, run: bool, now: float) -> None:
        """Start (``run``) or stop Timer[n] at ``now``; its registers follow."""
        t = self._timers[n]
        if not run:
            if t.running:
                t.base_ms = self._value(n, now)
                t.running = False
        elif not t.running:
            t.base_ms = join_i32(*self._words(n))
            t.running, t.since = True, now
        self.publish(now)

    def publish(self, now: float) -> None:
        """Write every running timer's value at ``now`` into its registers."""
        for n in range(1, len(self._timers)):
            if self._timers[n].running:
                low, high = split_i32(self._value(n, now))
                at = self._at(n)
                self._holding[at], self._holding[at + 1] = u16(low), u16(high)

    def written(self, start: int, end: int, now: float) -> None:
        """A client wrote registers ``start..end-1``: a running timer among them goes on
        counting from the written value."""
        for n in range(1, len(self._timers)):
            at = self._at(n)
            t = self._timers[n]
            if t.running and start < at + 2 and at < end:
                t.base_ms, t.since = join_i32(*self._words(n)), now

    def _at(self, n: int) -> int:
        return self._first + self._stride * (n - 1)

    def _words(self, n: int) -> tuple[int, int]:
        at = self._at(n)
        return self._holding[at], self._holding[at + 1]

    def _value(self, n: int, now: float) -> int:
        t = self._timers[n]
        if not t.running:
            return join_i32(*self._words(n))
        value = t.base_ms + int((now - t.since) * 1000)
        return max(-TIMER_LIMIT, min(TIMER_LIMIT, value))
