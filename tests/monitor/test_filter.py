"""The display filter (``f``, and the command line's filters handed to the screen) is
the command-line filter: same syntax, same RecordFilter, clear errors."""

from __future__ import annotations

import argparse

import pytest

from mbmon.commands.common import filter_text
from mbmon.filters import add_filter_options, build_filter
from mbmon.monitor.display_filter import FilterSyntaxError, parse_display_filter


@pytest.mark.parametrize(
    "argv",
    [
        ["--unit", "1,2", "--fc", "3,0x10", "--address", "200-251", "--grep", "PTP {A1"],
        ["--fc", "6", "--fc", "16"],
        ["--since", "+5s", "--until", "+1m"],
        [],
    ],
)
def test_the_command_line_filters_become_the_same_display_filter(argv: list[str]) -> None:
    parser = argparse.ArgumentParser()
    add_filter_options(parser)
    args = parser.parse_args(argv)
    text = filter_text(args)
    shown = parse_display_filter(text)
    if not argv:
        assert text == "" and shown is None
        return
    assert shown == build_filter(args, start_known=False)


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("--fc x", "x"),
        ("--unit", "--unit"),
        ("--bogus 1", "--bogus"),
        ("--grep 'open", "quotation"),
    ],
)
def test_a_bad_display_filter_says_why(text: str, why: str) -> None:
    with pytest.raises(FilterSyntaxError, match=why):
        parse_display_filter(text)
