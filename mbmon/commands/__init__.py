"""One module per command: each parses its options and wires sources, hub and listeners.

A command module exposes ``register(sub)``, which adds its subparser to the
``argparse`` sub-parsers ``sub`` and sets ``func`` to its ``run(args) -> int``.
:func:`mbmon.cli.build_parser` registers the modules of :data:`COMMANDS` in
order (the order of ``mbmon --help``); each is imported only to register.
"""

from __future__ import annotations

#: Command modules under ``mbmon.commands``, in the order ``mbmon --help`` lists them.
COMMANDS: list[str] = [
    "read",
    "decode",
    "replay",
    "info",
    "export",
    "sniff",
    "proxy",
    "sim",
    "demo",
    "report",
]
