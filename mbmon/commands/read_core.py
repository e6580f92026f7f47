"""``mbmon read`` by the compiled core: the common case (a capture file to plain lines
or JSON, no filters) without a Python object per ADU; it declines the rest before
writing a byte and the reference pipeline (:mod:`mbmon.commands.read`) reads then."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from mbmon.commands.common import EXIT_OK, err
from mbmon.commands.read_summary import report


def read_with_core(
    path: str,
    args: argparse.Namespace,
    view: Any,
    flt: Any,
    *,
    live: bool,
    progress: Any,
    annotator: Any = None,
) -> int | None:
    """``read`` by the compiled core when it covers the options and the input: its exit
    status; ``None`` when it declined (before writing anything: the Python pipeline
    then reads the input). ``--debug-core`` says which path ran and why. ``annotator``:
    the ``--profile`` annotator (the core annotates through it)."""
    from mbmon import core

    why = core.decline_for_options(args, live=live, flt=flt)
    if why is None:
        why = core.decline_for_profile(annotator)
    write = None
    broken: list[bool] = []
    if why is None and not args.quiet:
        from mbmon.sinks.console import utf8_buffer

        buffer = utf8_buffer(sys.stdout)
        if buffer is None:
            why = "stdout is not UTF-8"
        else:

            def write(data: bytes) -> None:
                if broken:
                    return
                try:
                    buffer.write(data)
                except BrokenPipeError:  # the reader went away (| head), as the hub does
                    from mbmon.hub import _quiet_stdout

                    broken.append(True)
                    _quiet_stdout()

    if why is None:
        run = core.read_file(
            path,
            ports=frozenset({502, *args.port}),
            timeout=args.timeout,
            view=view,
            as_json=args.json,
            write=write,
            progress=progress,
            detect=not args.no_detect,
            annotator=annotator,
        )
        progress.close()
        why = run.declined
    if why is not None:
        if args.debug_core:
            err(f"core: declined ({why}); the Python pipeline reads the input")
        return None
    if write is not None and not broken:
        try:
            sys.stdout.flush()
        except BrokenPipeError:
            from mbmon.hub import _quiet_stdout

            _quiet_stdout()
    if args.debug_core:
        err("core: the compiled core read the input")
    if not args.quiet:
        from mbmon.sinks.summary import Summary

        summary = Summary(None)
        core.fill_summary(summary, run.counts)
        report(summary, {}, args, timed=True)
    return EXIT_OK
