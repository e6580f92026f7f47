"""The monitor's display filter (``f``): the command line's filter options
(:mod:`mbmon.filters`), parsed from a line typed on the screen.
"""

from __future__ import annotations

import argparse
import shlex
from typing import Any


class FilterSyntaxError(ValueError):
    """A display filter the command-line filter syntax does not accept."""


class _FilterParser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # argparse would exit the program
        raise FilterSyntaxError(message)


def parse_display_filter(text: str) -> Any:
    """The :class:`~mbmon.filters.RecordFilter` for ``text`` in the command-line syntax
    (``--unit 1 --fc 3 --address 200-251 --grep PTP``); ``None`` for an empty text.
    Raises :class:`FilterSyntaxError` with the reason for anything else."""
    from mbmon.filters import FilterError, add_filter_options, build_filter

    if not text.strip():
        return None
    parser = _FilterParser(prog="f", add_help=False, exit_on_error=False)
    add_filter_options(parser)
    try:
        args = parser.parse_args(shlex.split(text))
        return build_filter(args, start_known=False)
    except (FilterError, ValueError, argparse.ArgumentError) as exc:
        raise FilterSyntaxError(str(exc)) from None
