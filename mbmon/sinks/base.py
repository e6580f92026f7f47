"""Sinks: every writer and view is a listener of the hub (DESIGN rule 7).

The listener contract (its hooks, every one optional, ``close`` included) is
:data:`mbmon.hub.HOOKS`, in :mod:`mbmon.hub` only; the hub calls only the hooks
a listener defines. A sink is a listener that writes a file, opened by
:func:`open_sink` from the suffix of ``-w FILE`` or ``export -o FILE``; sink
modules are imported only when used. There is one contract for both: ``read``
hands a sink the records it decodes, ``export`` the records a log stored
(:class:`~mbmon.stored.StoredRecord`, whose line and JSON object
:mod:`mbmon.format` gives as they were recorded), through the same hooks, so a
suffix registered once in :data:`SINKS` serves both.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Self

if TYPE_CHECKING:
    from mbmon.format import View


class SinkError(Exception):
    """A sink cannot be opened or written (bad suffix, unwritable path); the message says why."""


def _default_view() -> View:
    """A context's view when none is given (:mod:`mbmon.format` imported when first needed:
    ``mbmon.cli`` imports this module for :class:`SinkError` in every run)."""
    from mbmon.format import View

    return View()


@dataclass(frozen=True, slots=True)
class SinkContext:
    """What a sink may want to know besides the records: labels, provenance, semantics in force.

    ``profile_specs``, ``timeout`` and ``baud`` are the analysis settings the
    records were made with (``--profile`` values in order, ``--timeout`` in
    seconds, ``--baud``), given directly so that a log can store them and
    ``replay --redecode`` decode its raw bytes the same way; ``command_line``
    is provenance only.
    """

    view: View = field(default_factory=_default_view)
    command_line: list[str] = field(default_factory=list)
    source: str = ""
    profiles: list[tuple[str, str]] = field(default_factory=list)  # (name, TOML text)
    profile_specs: list[str] = field(default_factory=list)
    timeout: float = 1.0
    baud: int | None = None


class SinkBase:
    """A file-writing listener: a context manager whose ``close()`` always runs once."""

    def close(self) -> None:
        return None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


#: suffix -> (module, class); imported lazily so that ``import mbmon`` stays light.
SINKS: dict[str, tuple[str, str]] = {
    ".mcap": ("mbmon.sinks.mcap", "McapSink"),
    ".jsonl": ("mbmon.sinks.jsonl", "JsonlSink"),
    ".csv": ("mbmon.sinks.csvfile", "CsvSink"),
    ".txt": ("mbmon.sinks.text", "TextSink"),
    ".pcap": ("mbmon.sinks.pcap", "PcapSink"),
    ".pcapng": ("mbmon.sinks.pcap", "PcapngSink"),
    ".parquet": ("mbmon.sinks.parquet", "ParquetSink"),  # needs the 'parquet' extra
}


def open_sink(path: str | Path, ctx: SinkContext) -> SinkBase:
    """Open the sink that the suffix of ``path`` names; :class:`SinkError` when none does."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SINKS:
        known = ", ".join(sorted(SINKS))
        raise SinkError(
            f"{path}: unknown output format {suffix or '(no suffix)'!r}; use one of {known}"
        )
    module_name, class_name = SINKS[suffix]
    cls = getattr(importlib.import_module(module_name), class_name)
    try:
        sink: SinkBase = cls(path, ctx)
    except OSError as exc:
        raise SinkError(f"{path}: cannot write: {exc.strerror or exc}") from None
    return sink
