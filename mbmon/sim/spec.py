"""The HRSS data the simulator is driven by, from :mod:`mbmon.semantics` (one import site).

The simulator knows no register address or command layout of its own: the
address map comes from the ``hrss`` register profile (``profiles/hrss.toml``)
and the command layouts, ranges and return layouts from
``profiles/hrss_commands.toml``, the same data the analyzer reads. This module
is the only place in :mod:`mbmon.sim` that imports from :mod:`mbmon.semantics`.
"""

from __future__ import annotations

from functools import lru_cache

from mbmon.semantics.hrss import (
    CommandSpec,
    Decoded,
    Layout,
    Spec,
    decode_command,
    decode_returns,
    load_spec,
)
from mbmon.semantics.hrss import Field as CommandField
from mbmon.semantics.regmap import TABLES, Profile, load_profile
from mbmon.semantics.words import join_i32, s16, split_i32, u16

__all__ = [
    "TABLES",
    "CommandField",
    "CommandSpec",
    "Decoded",
    "Layout",
    "Profile",
    "Spec",
    "address_map",
    "command_spec",
    "decode_command",
    "decode_returns",
    "hrss_profile",
    "join_i32",
    "s16",
    "split_i32",
    "u16",
]


@lru_cache(maxsize=1)
def hrss_profile() -> Profile:
    """The built-in ``hrss`` register map."""
    return load_profile("hrss")


def command_spec() -> Spec:
    """The built-in HRSS command layouts (Tables 16-43)."""
    return load_spec()


@lru_cache(maxsize=1)
def address_map() -> dict[str, tuple[tuple[int, int], ...]]:
    """Per table, the merged ``[start, end)`` address ranges the ``hrss`` profile defines.

    An access that leaves these ranges is answered with exception 02.
    """
    out: dict[str, tuple[tuple[int, int], ...]] = {}
    profile = hrss_profile()
    for table in TABLES:
        spans = sorted((e.address, e.end_address()) for e in profile.entries(table))
        merged: list[tuple[int, int]] = []
        for start, end in spans:
            if merged and start <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(merged[-1][1], end))
            else:
                merged.append((start, end))
        out[table] = tuple(merged)
    return out
