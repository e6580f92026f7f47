"""Week-long captures in rotating files: ``-w cell.mcap --rotate 1h --keep 168``.

This module owns the ring of files behind one ``-w`` target: when a file is
finished and the next one begun (every period of capture time, aligned to
whole periods since the epoch as dumpcap's ``interval`` is, and/or when a file
reached a size on disk), what the files are called, and which are removed.

Every format works the same way, through the sink contract
(:mod:`mbmon.sinks.base`): :class:`RotatingSink` is a listener that holds one
ordinary sink at a time, opened with :func:`~mbmon.sinks.base.open_sink` from
the target's suffix, and passes every hook on to it. At a rotation the current
sink is closed (so each file is finished and valid on its own: an MCAP with
its summary and index, a pcap, complete lines) and the next is opened for the
item that crossed the boundary; nothing is dropped or written twice, so the
counts across the files equal one file's. A new file is opened only when an
item comes (an idle hour leaves no empty file); a file whose period ended is
finished on the next tick.

Names carry a sequence number and the capture time of the file's first item,
in UTC: ``cell.mcap`` rotates into ``cell_00001_20261126T120000Z.mcap``,
``cell_00002_20261126T130000Z.mcap``, ... (the number keeps the order when two
files start in one second). With ``keep``, after each new file the oldest
files of this run beyond ``keep`` are removed (files of earlier runs are never
touched). The listener's ``files`` lists the files of the ring still on disk.
"""

from __future__ import annotations

import importlib
import math
import os
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mbmon.hub import hooks_of
from mbmon.sinks.base import SINKS, SinkBase, SinkContext, SinkError, open_sink

__all__ = ["RotatingSink", "RotationError", "parse_rotate", "rotated_name"]

#: Hook calls between two looks at the current file's size on disk.
SIZE_CHECK_EVERY = 256

_SIZE = re.compile(r"^\s*(\d+(?:\.\d*)?)\s*([kmgt]i?b|b)\s*$", re.IGNORECASE)
_SIZE_UNITS = {
    "b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12,
    "kib": 1 << 10, "mib": 1 << 20, "gib": 1 << 30, "tib": 1 << 40,
}  # fmt: skip
#: The input hooks a rotating sink passes on to the file of the item's time
#: (those of :data:`mbmon.hub.HOOKS` its sink class has; ``on_tick`` and
#: ``close`` it has itself).
_PASSED = ("on_chunk", "on_event", "on_records", "on_record")


class RotationError(ValueError):
    """A ``--rotate`` value that is neither a duration nor a size."""


def parse_rotate(values: list[str]) -> tuple[float | None, int | None]:
    """``--rotate`` values (each a duration such as ``1h`` or a size such as
    ``100MB``; one of each at most) as ``(seconds, bytes)``."""
    from mbmon.timefmt import TimeParseError, parse_duration

    seconds: float | None = None
    size: int | None = None
    for text in values:
        match = _SIZE.match(text)
        if match:
            number = float(match.group(1)) * _SIZE_UNITS[match.group(2).lower()]
            if size is not None or number < 1:
                raise RotationError(f"--rotate {text!r}: one size of at least 1 byte")
            size = int(number)
            continue
        if re.fullmatch(r"\s*[\d.]+\s*", text):
            raise RotationError(f"--rotate {text!r}: give a unit (1h, 30min, 100MB)")
        try:
            value = parse_duration(text)
        except TimeParseError:
            raise RotationError(
                f"--rotate {text!r}: neither a duration (30min, 1h, 1d) nor a size (100MB, 1GiB)"
            ) from None
        if seconds is not None:
            raise RotationError(f"--rotate {text!r}: one duration at most")
        seconds = value
    return seconds, size


def rotated_name(target: Path, number: int, start: float) -> Path:
    """The name of the ``number``-th file of the ring of ``target``, begun at
    ``start`` (epoch seconds): ``STEM_NNNNN_YYYYmmddTHHMMSSZ.SUFFIX``."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(math.floor(start)))
    return target.with_name(f"{target.stem}_{number:05d}_{stamp}{target.suffix}")


class RotatingSink(SinkBase):
    """One ``-w`` target as a ring of finished files (see the module docstring).

    ``every``: seconds of capture time per file (aligned to whole periods since
    the epoch); without ``every`` and ``max_bytes`` a file ends only when
    :meth:`end_file` is called (a trigger's window); ``max_bytes``: a file is
    finished once it holds that much on
    disk (looked at every :data:`SIZE_CHECK_EVERY` items and on each tick, so
    a file may exceed it by what was written meanwhile); ``keep``: files kept
    at most. ``opener`` opens one file of the ring (default:
    :func:`~mbmon.sinks.base.open_sink` with ``ctx``).
    """

    def __init__(
        self,
        target: str | Path,
        ctx: SinkContext,
        *,
        every: float | None = None,
        max_bytes: int | None = None,
        keep: int | None = None,
        opener: Callable[[Path], SinkBase] | None = None,
    ) -> None:
        self.path = Path(target)
        self.ctx = ctx
        self.every = every
        self.max_bytes = max_bytes
        self.keep = keep
        self._opener = opener or (lambda path: open_sink(path, ctx))
        suffix = self.path.suffix.lower()
        if suffix not in SINKS:
            known = ", ".join(sorted(SINKS))
            raise SinkError(f"{self.path}: unknown output format {suffix!r}; use one of {known}")
        module_name, class_name = SINKS[suffix]
        cls = getattr(importlib.import_module(module_name), class_name)
        # the hub calls only the hooks a listener has: those of the sink class
        has = hooks_of(cls)
        for hook in _PASSED:
            if getattr(has, hook) is not None:
                setattr(self, hook, getattr(self, "_" + hook))
        if not self.path.parent.is_dir():
            raise SinkError(f"{self.path}: cannot write: no such directory {self.path.parent}")
        self._sink: Any = None
        self._current: Path | None = None
        self._until = math.inf  # capture time at which the current file ends
        self._number = 0
        self._calls = 0
        self._closed = False
        #: the files of the ring still on disk, oldest first
        self.files: list[Path] = []

    # ------------------------------------------------------------------ the ring

    def _open(self, ts: float) -> Any:
        """Begin the next file with an item stamped ``ts``."""
        self._number += 1
        path = rotated_name(self.path, self._number, ts)
        self._sink = self._opener(path)
        self._current = path
        self.files.append(path)
        every = self.every
        self._until = (math.floor(ts / every) + 1) * every if every is not None else math.inf
        self._calls = 0
        if self.keep is not None:
            while len(self.files) > self.keep:
                self._remove(self.files.pop(0))
        return self._sink

    def _remove(self, path: Path) -> None:
        for name in (path, path.with_name(f"{path.stem}.tcp{path.suffix}"),
                     path.with_name(f"{path.stem}.rtu{path.suffix}")):  # fmt: skip
            try:
                os.remove(name)
            except FileNotFoundError:
                continue
            except OSError as exc:
                raise OSError(exc.errno, exc.strerror, str(name)) from exc

    def end_file(self) -> None:
        """End the current file now (a trigger window closed): the next item
        begins the next file of the ring."""
        self._finish()

    def _finish(self) -> None:
        """Close the current file (finished and valid on its own)."""
        sink, self._sink = self._sink, None
        self._until = math.inf
        if sink is not None:
            sink.close()

    def _full(self) -> bool:
        """Whether the current file reached ``max_bytes``: the position of the sink's
        file object when it has one (bytes still in its buffer count), else the
        size on disk."""
        if self.max_bytes is None or self._current is None:
            return False
        f = getattr(self._sink, "_f", None)
        try:
            size = f.tell() if f is not None else os.path.getsize(self._current)
        except (OSError, ValueError, AttributeError):
            return False
        return bool(size >= self.max_bytes)

    def _sink_for(self, ts: float) -> Any:
        """The sink an item stamped ``ts`` goes to, rotating first when it is due."""
        sink = self._sink
        if sink is not None:
            if ts >= self._until:
                self._finish()
                sink = None
            elif self.max_bytes is not None:
                self._calls += 1
                if self._calls >= SIZE_CHECK_EVERY:
                    self._calls = 0
                    if self._full():
                        self._finish()
                        sink = None
        if sink is None:
            if self._closed:
                raise SinkError(f"{self.path}: written after it was closed")
            sink = self._open(ts)
        return sink

    # ------------------------------------------------------------------ listener hooks

    def _on_chunk(self, chunk: Any) -> None:
        self._sink_for(chunk.ts).on_chunk(chunk)

    def _on_event(self, event: Any) -> None:
        self._sink_for(event.ts).on_event(event)

    def _on_record(self, record: Any) -> None:
        self._sink_for(record.ts).on_record(record)

    def _on_records(self, records: list[Any]) -> None:
        start = 0
        for i, record in enumerate(records):
            if record.ts >= self._until:
                if i > start:
                    self._sink_for(records[start].ts).on_records(records[start:i])
                start = i
                self._finish()
        if start < len(records):
            self._sink_for(records[start].ts).on_records(records[start:])

    def on_tick(self, now: float) -> None:
        """Finish a file whose period ended or that is full; pass the tick on."""
        if self._sink is None:
            return
        if now >= self._until or self._full():
            self._finish()
            return
        hooks_of(self._sink).tick(now)

    def close(self) -> None:
        """Finish the current file (the ring stays as it is)."""
        if self._closed:
            return
        self._closed = True
        self._finish()
