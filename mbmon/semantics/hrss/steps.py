"""What the HRSS session keeps per write and per command, and what one step produces.

:class:`Exec` (one executed command, R200 = 1 to its end), :class:`Write` (a
write request applied to the holding image until its answer), :class:`StepOut`
(the notes, command steps and state change of one step or tick, in order) and
:class:`LiveImage` (a register image brought up to date when read).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from mbmon.model import Annotation, CommandUpdate, Frame, Phase, Stream
from mbmon.semantics.hrss.render import Decoded
from mbmon.semantics.hrss.spec import CommandSpec
from mbmon.semantics.session import annotation

__all__ = ["Exec", "LiveImage", "StepOut", "Write", "pop_oldest", "write_key"]


@dataclass(slots=True)
class Exec:
    """One executed command, from R200 = 1 to its end."""

    decoded: Decoded
    spec: CommandSpec | None
    t0: float
    stream: Stream
    done: bool = False  # IR200 showed 1/2, or the execute was rejected
    status: int | None = None
    settled: bool = False  # completion seen another way (motion ended, hold-to-run stopped)
    looked: bool = False  # the client read IR200 or IR524 after the execute
    moving: bool = False  # IR524 showed Running/Hold/Delay after the execute
    warned: bool = False  # "never completes" already said
    return_seen: set[int] = field(default_factory=set)
    returned: tuple[Any, ...] | None = None


@dataclass(slots=True)
class Write:
    """A write request applied to the holding image, kept until its answer."""

    old: dict[int, int | None]
    new: dict[int, int]
    execute: Exec | None = None


class LiveImage(Mapping[int, int]):
    """A read-only view of a register image that ``image()`` brings up to date when read."""

    __slots__ = ("_image",)

    def __init__(self, image: Callable[[], dict[int, int]]) -> None:
        self._image = image

    def __getitem__(self, address: int) -> int:
        return self._image()[address]

    def __iter__(self) -> Iterator[int]:
        return iter(self._image())

    def __len__(self) -> int:
        return len(self._image())

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._image()!r})"


def write_key(req: Frame) -> tuple[Any, ...]:
    return (req.ts, req.stream.id, req.tid, req.raw)


def pop_oldest(writes: dict[tuple[Any, ...], Write]) -> tuple[tuple[Any, ...], Write]:
    key = next(iter(writes))
    return key, writes.pop(key)


class StepOut:
    """What one step (or tick) produces, gathered in order, stamped ``ts`` on ``stream``.

    One per session, made ready for each step by
    :meth:`~mbmon.semantics.hrss.session.HrssSession.follow`:
    ``notes`` is the list the step's notes go to, ``commands`` is ``None``
    until a command step is made.
    """

    __slots__ = ("commands", "notes", "state", "state_changed", "stream", "ts", "unit")

    def __init__(self, unit: int, stream: Stream, state: dict[str, float]) -> None:
        self.unit = unit
        self.state = state  # the session's robot state (copied into a changed step)
        self.ts = 0.0
        self.stream = stream
        self.notes: list[str] = []
        self.commands: list[CommandUpdate] | None = None
        self.state_changed = False

    def note(self, text: str) -> None:
        self.notes.append(text)

    def command(
        self,
        phase: Phase,
        text: str,
        code: int | None,
        *,
        params: Mapping[str, Any],
        duration: float | None = None,
        note: str | None = None,
    ) -> None:
        update = CommandUpdate(
            ts=self.ts,
            stream=self.stream,
            unit=self.unit,
            phase=phase,
            text=text,
            code=code,
            duration=duration,
            params=MappingProxyType(dict(params)),
        )
        if self.commands is None:
            self.commands = [update]
        else:
            self.commands.append(update)
        if note is not None:
            self.notes.append(note)

    def warn(self, text: str, *, kind: str, code: int | None) -> None:
        self.command(Phase.WARNING, text, code, params={"warning": kind}, note=f"warning: {text}")

    def annotation(self) -> Annotation:
        commands = tuple(self.commands) if self.commands else ()
        return annotation(self.notes, commands, dict(self.state) if self.state_changed else None)
