"""The bounded caches of one view's JSON lines: what :mod:`mbmon.jsonfmt` cuts once
out of a full encoding and fills in per record.

A :class:`JsonLineCache` belongs to one :class:`~mbmon.format.View` (its
``json_cache``): whoever writes JSON lines through that view shares it, and it goes
away with the view. It holds data only; :mod:`mbmon.jsonfmt` makes and checks what
goes in. Every table is bounded in entries, the parts also in bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mbmon.model import Direction, Frame, RecordKind, Stream

#: entries each table may hold before it is emptied
CACHE_SIZE = 8192
#: bytes the fixed parts may hold before they are emptied (register answers are long)
CACHE_BYTES = 1 << 20
#: entries of the seen-once table (keys only: cheap)
SEEN_ONCE_SIZE = 16384
#: stream directions whose heads are kept
HEADS_SIZE = 65536


@dataclass(slots=True)
class JsonLineCache:
    """The fixed JSON parts of one view's frame records.

    ``parts``: by (id(pdu), id(request pdu), kind, unit, crc_ok): (pdu, request pdu,
    text from "unit" to "line":, monitor hex, generic note as JSON, the same
    JSON-escaped, text from "crc_ok" to "latency_ms":, text from "malformed" to
    "request_index":, end of the object). The PDUs are kept so that an id is never
    taken for a later object's.

    ``seen_once``: keys (as ``parts``') of frame records encoded once in full; their
    parts are made on a second sighting. On a cell's capture most answers hold
    values never seen before and never seen again; making their parts costs more
    than encoding them whole, and only a repeat pays it back. A reused id only
    makes parts early.

    ``read_templates``: answers to reads whose values change every poll (a robot's
    position, a counter): per (id(request pdu), unit, crc_ok, fc, PDU length), the
    fixed parts around the values, from the first answer whose parts were checked
    against its full encoding: (request pdu, text from "unit" to "values":, the
    note's JSON up to its values, text from "crc_ok" to "latency_ms":, text from
    "malformed" to "request_index":, end of the object, values are bits); ``(request
    pdu, None)`` when that request's answers take the general path.

    ``heads``: per stream direction, (stream, JSON from "stream" to "tid":, label
    JSON-escaped), in UTF-8; the view empties them when its labels change.

    ``keys_checked``: a full encoding confirmed the key texts that parts are made of
    value by value.
    """

    parts: dict[tuple[Any, ...], tuple[Any, ...]] = field(default_factory=dict)
    seen_once: dict[tuple[Any, ...], None] = field(default_factory=dict)
    read_templates: dict[tuple[Any, ...], tuple[Any, ...]] = field(default_factory=dict)
    heads: dict[tuple[int, Direction], tuple[Stream, bytes, bytes]] = field(default_factory=dict)
    keys_checked: bool = False
    #: bytes held in ``parts``
    held: int = 0

    def seen(self, key: tuple[Any, ...]) -> None:
        """Remember a frame record's parts key as seen once (bounded)."""
        if len(self.seen_once) >= SEEN_ONCE_SIZE:
            self.seen_once.clear()
        self.seen_once[key] = None

    def keep_parts(self, parts: tuple[Any, ...], kind: RecordKind, frame: Frame) -> None:
        """Cache a frame record's fixed JSON parts (bounded in entries and in bytes)."""
        if len(self.parts) >= CACHE_SIZE or self.held > CACHE_BYTES:
            self.parts.clear()
            self.held = 0
        self.parts[(id(parts[0]), id(parts[1]), kind, frame.unit, frame.crc_ok)] = parts
        self.held += len(parts[2]) + len(parts[3]) + 2 * len(parts[4]) + len(parts[8])

    def keep_template(self, key: tuple[Any, ...], template: tuple[Any, ...]) -> None:
        """Cache the template of a read's answers (bounded)."""
        if len(self.read_templates) >= CACHE_SIZE:
            self.read_templates.clear()
        self.read_templates[key] = template

    def keep_head(self, key: tuple[int, Direction], head: tuple[Stream, bytes, bytes]) -> None:
        """Cache a stream direction's head (bounded)."""
        if len(self.heads) > HEADS_SIZE:
            self.heads.clear()
        self.heads[key] = head
