"""What every command shares, in one import: exit codes, usage errors, signals, the
exit status, the listener order, ``-c``, option groups, progress and outputs.

Commands are wiring (DESIGN): parse options with these groups → build sources
and listeners → ``hub.run`` → one exit status. The pieces live in small modules,
all re-exported here (``from mbmon.commands.common import X``):

- :mod:`~mbmon.commands.ending` — how a run ends. ``EXIT_*``, :class:`UsageError`,
  :func:`err`; the one signal handler (:func:`install_signal_handlers`, installed
  by ``mbmon.cli.main``: SIGINT/SIGTERM raise :class:`Interrupted`, a
  ``KeyboardInterrupt``); :func:`stop_on_signals` for commands that run until
  stopped (the signal calls ``stop(n)`` instead of raising); and the one
  exit-status decision :func:`exit_status` (an output failed → 1; a signal → 128 +
  its number, unless the command runs until a signal; bad input → 1; else 0).
- :mod:`~mbmon.commands.listeners` — the one listener order,
  :func:`attach_outputs`: logs first, then the screen, then the summary (a
  printed record has always been logged); and the one ``-c N``
  (:func:`add_count_option`, :class:`FrameBudget`): frames that pass the filters,
  Connect/Disconnect events do not count, every output ends at the N-th.
- :mod:`~mbmon.commands.values` — argparse value types;
  :mod:`~mbmon.commands.options` — option groups.
- :mod:`~mbmon.commands.outputs` — annotator, view and filter, ``-w`` logs,
  rotation, triggers, Foxglove, and the words for an endpoint that cannot open.
- :mod:`~mbmon.commands.screen` — the console or live monitor, figures, progress.

A command reading until its input ends::

    interrupted = False
    try:
        hub.run_items(items)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        hub.close()
    return exit_status(hub, interrupted=interrupted)

A command running until it is stopped::

    with stop_on_signals(lambda n: hub.stop()):
        hub.run()
    hub.close()
    return exit_status(hub, until_signal=True)
"""

from __future__ import annotations

from mbmon.commands.ending import (
    EXIT_BAD_INPUT,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    STOP_SIGNALS,
    Interrupted,
    SignalStop,
    UsageError,
    err,
    exit_status,
    install_signal_handlers,
    interrupted_status,
    loop_stops_on_signals,
    output_failed,
    pending_signal,
    received_signal,
    stop_on_signals,
)
from mbmon.commands.listeners import (
    COUNT_HELP,
    FrameBudget,
    Limited,
    add_count_option,
    attach_outputs,
)
from mbmon.commands.options import (
    add_capture_run_options,
    add_interface_options,
    add_live_options,
    add_output_options,
    add_port_options,
    add_serial_line_options,
    add_serial_tap_options,
    add_view_options,
)
from mbmon.commands.outputs import (
    FOXGLOVE_DEFAULT,
    add_foxglove_option,
    check_outputs,
    check_rotation,
    foxglove_address,
    listen_error,
    make_annotator,
    open_foxglove,
    open_log,
    open_logs,
    open_trigger,
    profile_sources,
    serial_open_error,
    view_and_filter,
    why_not,
)
from mbmon.commands.screen import (
    Figures,
    Progress,
    filter_text,
    open_console,
    run_live,
    wants_state_panel,
)
from mbmon.commands.values import (
    endpoint,
    exception_code,
    listen_address,
    parse_address,
    port,
    positive,
    positive_int,
    split_host_port,
    unit_id,
    whole_number,
)

__all__ = [
    "COUNT_HELP",
    "EXIT_BAD_INPUT",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USAGE",
    "FOXGLOVE_DEFAULT",
    "STOP_SIGNALS",
    "Figures",
    "FrameBudget",
    "Interrupted",
    "Limited",
    "Progress",
    "SignalStop",
    "UsageError",
    "add_capture_run_options",
    "add_count_option",
    "add_foxglove_option",
    "add_interface_options",
    "add_live_options",
    "add_output_options",
    "add_port_options",
    "add_serial_line_options",
    "add_serial_tap_options",
    "add_view_options",
    "attach_outputs",
    "check_outputs",
    "check_rotation",
    "endpoint",
    "err",
    "exception_code",
    "exit_status",
    "filter_text",
    "foxglove_address",
    "install_signal_handlers",
    "interrupted_status",
    "listen_address",
    "listen_error",
    "loop_stops_on_signals",
    "make_annotator",
    "open_console",
    "open_foxglove",
    "open_log",
    "open_logs",
    "open_trigger",
    "output_failed",
    "parse_address",
    "pending_signal",
    "port",
    "positive",
    "positive_int",
    "profile_sources",
    "received_signal",
    "run_live",
    "serial_open_error",
    "split_host_port",
    "stop_on_signals",
    "unit_id",
    "view_and_filter",
    "wants_state_panel",
    "whole_number",
    "why_not",
]
