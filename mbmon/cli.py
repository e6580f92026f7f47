"""Command-line entry point (argument parsing and wiring only)."""

from __future__ import annotations


def main(argv: list[str] | None = None) -> int:
    raise SystemExit("mbmon: not built yet")
