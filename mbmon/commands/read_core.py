"""``mbmon read`` by the compiled core: the common case (capture files to plain lines
or JSON, with the view options, filters and ``-c``) without a Python object per ADU;
it declines the rest before writing a byte and the reference pipeline
(:mod:`mbmon.commands.read`) reads then."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from mbmon.commands.common import EXIT_BAD_INPUT, EXIT_OK, err, profile_sources
from mbmon.commands.ending import interrupted_status
from mbmon.commands.read_summary import report


def core_hand_off(
    sources: list[Any], args: argparse.Namespace, view: Any, flt: Any, annotator: Any = None
) -> int | None:
    """The one place where ``read`` hands its run to the compiled core: its inputs are
    capture files (:class:`~mbmon.sources.files.CaptureFileSource`, not yet opened),
    which the core reads whole by their paths, one after another, when it covers them.
    The exit status when it did; ``None`` when the sources are to be read through the
    hub (a raw RTU dump, or the core declined, before writing anything)."""
    from mbmon.sources.files import CaptureFileSource

    done = None
    bus = len(sources) == 1 and isinstance(sources[0], CaptureFileSource) and _bus(sources[0])
    if len(sources) == 1 and args.rtu_raw:
        done = read_rtu_with_core(sources[0], args, view, flt, annotator)
    elif bus:
        done = read_rtu_with_core(sources[0], args, view, flt, annotator, bus=True)
    elif not sources or not all(isinstance(source, CaptureFileSource) for source in sources):
        if args.debug_core and len(sources) > 1:
            err("core: declined (several inputs of this kind); the Python pipeline reads the input")
    elif len(sources) == 1 and sources[0].mode == "stream":
        done = read_pipe_with_core(sources[0], args, view, flt, annotator)
    else:
        live = any(source.mode == "stream" for source in sources)
        done = read_with_core(
            [source.path for source in sources],
            args,
            view,
            flt,
            live=live,
            progress=[source.progress for source in sources],
            annotator=annotator,
        )
    if done is None and args.debug_core and (args.rtu_raw or args.rtu_port or bus):
        from mbmon import core

        err(f"core: {core.rtu_status(args.baud)}")
    return done


def read_with_core(
    paths: list[str],
    args: argparse.Namespace,
    view: Any,
    flt: Any,
    *,
    live: bool,
    progress: list[Any],
    annotator: Any = None,
) -> int | None:
    """``read`` by the compiled core when it covers the options and the inputs (read one
    after another into one output): its exit status; ``None`` when it declined (before
    writing anything: the Python pipeline then reads the inputs). ``--debug-core`` says
    which path ran and why. ``annotator``: the ``--profile`` annotator (the core
    annotates through it)."""
    from mbmon import core
    from mbmon.sinks.base import SinkError

    why = core.decline_for_options(args, live=live, flt=flt)
    if why is None:
        why = core.decline_for_profile(annotator)
    raw = None
    if why is None and not args.quiet:
        raw, why = _raw_stdout()
    write = None if raw is None else raw.write

    if why is None:
        log = _log_opener(paths, args, view) if args.write else None
        try:
            run = core.read_files(
                paths,
                ports=frozenset({502, *args.port}),
                timeout=args.timeout,
                view=view,
                as_json=args.json,
                write=write,
                progress=progress,
                detect=not args.no_detect,
                log=log,
                annotator=annotator,
                flt=flt,
                count=args.count,
            )
        except SinkError as exc:  # the log could not be opened or written (it was closed)
            for bar in progress:
                bar.close()
            err(str(exc))
            return EXIT_BAD_INPUT
        for bar in progress:
            bar.close()
        why = run.declined
    if why is not None:
        if args.debug_core:
            err(f"core: declined ({why}); the Python pipeline reads the input")
        return None
    _flush_stdout(raw)
    if args.debug_core:
        err("core: the compiled core read the input")
    if not args.quiet:
        from mbmon.sinks.summary import Summary

        summary = Summary(view if args.robot else None)
        core.fill_summary(summary, run.counts)
        report(summary, {}, args, timed=True)
    if run.interrupted:
        log_path = Path(args.write[0])  # as the sink names it (McapSink.path)
        err(f"interrupted; {log_path} was finished and is complete up to here")
        return interrupted_status()
    return EXIT_OK


def read_pipe_with_core(
    source: Any, args: argparse.Namespace, view: Any, flt: Any, annotator: Any = None
) -> int | None:
    """``read`` of one capture on a pipe, FIFO or stdin (``-``) by the core's streaming
    entry (:class:`mbmon.core.live.PipeCore`) with the reference's wiring around it:
    its exit status; ``None`` when the options decline it (before anything is read:
    the Python pipeline then reads the input). The core writes the lines while it
    covers the records; the first record, tick or end it does not cover hands the
    whole run to the reference dissector and the hub's pipeline. ``--debug-core``
    says which path ran and why."""
    from mbmon.core.live import decline_for_pipe

    why = decline_for_pipe(args, flt=flt, annotator=annotator)
    raw = None
    if why is None and not args.quiet:
        raw, why = _raw_stdout()
    if why is not None:
        if args.debug_core:
            err(f"core: declined ({why}); the Python pipeline reads the input")
        return None
    from mbmon.sources.pcapfile import CaptureError, open_records

    try:  # as the source opens it: one line before any output
        opened = open_records(source.path, source.progress)
    except CaptureError as exc:
        err(str(exc))
        return EXIT_BAD_INPUT
    return _run_pipe(source, opened, args, view, flt, raw)


def _run_pipe(
    source: Any, opened: Any, args: argparse.Namespace, view: Any, flt: Any, raw: Any
) -> int:
    """The run of :func:`read_pipe_with_core`: the hub, its listeners (the console and
    the summary, as the reference attaches them), the core's stage, the pipe's records
    through it, the summary and the exit status."""
    from mbmon.commands.common import attach_outputs, exit_status
    from mbmon.core.live import PipeCore, add_counts, run_pipe
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sinks.summary import Summary
    from mbmon.sources.dissect import Dissector

    hub = Hub(Pipeline(None, PipelineConfig(timeout=args.timeout, baudrate=args.baud)))
    summary = None if args.quiet else Summary(view if args.robot else None)
    screen: Any = None
    if not args.quiet:
        from mbmon.sinks.console import ConsoleListener

        screen = ConsoleListener(sys.stdout, view, as_json=args.json, live=True)
        if flt is not None and flt.active:
            from mbmon.sinks.select import Selection

            screen = Selection([screen], view, flt)
    budget = None
    if args.count:
        from mbmon.commands.common import FrameBudget

        budget = FrameBudget(args.count, hub.enough, flt, view)
    attach_outputs(hub, logs=[], screen=screen, summary=summary, budget=budget)
    config = source.config
    dissector = Dissector(
        config,
        Path(source.path).name,
        new_stream=hub.new_stream,
        idle_timeout=None,
        hole_timeout=None,
    )
    stage = PipeCore(
        ports=config.tcp_ports,
        timeout=args.timeout,
        view=view,
        as_json=args.json,
        write=None if raw is None else raw.write,
        flush=None,
        new_stream=hub.new_stream,
        dissector=dissector,
        pipeline=hub.pipeline,
        detect=config.detect,
        flt=flt,
        count=args.count,
        budget=budget,
    )
    interrupted = False
    try:
        run_pipe(stage, hub, opened, source.path)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        hub.close()
    _flush_stdout(raw)
    if args.debug_core:
        then = "" if stage.handed is None else f", then the Python pipeline ({stage.handed})"
        err(f"core: the compiled core read the input{then}")
    if summary is not None:
        add_counts(summary, stage.counts())
        summary.robot_seen = summary.robot_seen or stage.counts()["robot_seen"]
        report(summary, stage.stats(), args, timed=True)
    if not interrupted and hub.errors:
        err(hub.errors[-1])
    return exit_status(hub, interrupted=interrupted)


def read_rtu_with_core(
    source: Any,
    args: argparse.Namespace,
    view: Any,
    flt: Any,
    annotator: Any = None,
    *,
    bus: bool = False,
) -> int | None:
    """``read --rtu-raw FILE`` (a raw dump), or with ``bus`` ``read BUS.pcap`` (a
    capture of RTU buses, link type 147, USER0, at the capture's times), by the
    compiled core (the framer's frames paired and written by the core) when it
    covers the options and the input: its exit status; ``None`` when it declined,
    before writing anything (the Python pipeline then reads the input).
    ``--debug-core`` says which path ran and why."""
    from mbmon import core

    if bus:
        why = core.decline_for_bus(args, live=False, flt=flt, annotator=annotator)
    else:
        live = source.mode == "stream"
        why = core.decline_for_rtu(args, live=live, flt=flt, annotator=annotator)
    raw = None
    if why is None and not args.quiet:
        raw, why = _raw_stdout()
    if why is None:
        common: dict[str, Any] = {
            "timeout": args.timeout,
            "view": view,
            "as_json": args.json,
            "write": None if raw is None else raw.write,
            "flt": flt,
            "count": args.count,
        }
        if bus:
            run = core.read_bus_file(source.path, **common)
        else:
            run = core.read_rtu_file(source.path, read_size=source.chunk_size, **common)
        why = run.declined
    if why is not None:
        if args.debug_core:
            err(f"core: declined ({why}); the Python pipeline reads the input")
        return None
    _flush_stdout(raw)
    if args.debug_core:
        what = "an RTU bus: framing, pairing and lines" if bus else "RTU framing, pairing and lines"
        err(f"core: the compiled core read the input ({what})")
    if not args.quiet:
        from mbmon.sinks.summary import Summary

        summary = Summary(view if args.robot else None)
        core.fill_rtu_summary(summary, run.counts)
        report(summary, {}, args, timed=bus)
    return EXIT_OK


def _bus(source: Any) -> bool:
    """Whether ``source`` (a capture file) is a capture of an RTU bus (USER0)."""
    from mbmon import core

    return source.mode != "stream" and core.bus_capture(source.path)


def _raw_stdout() -> tuple[Any, str | None]:
    """The core's way to stdout (bytes to its buffer), or why there is none (a stdout
    that is not UTF-8 declines the core: the reference's console escapes for it)."""
    from mbmon.sinks.console import RawStdout, utf8_buffer

    buffer = utf8_buffer(sys.stdout)
    if buffer is None:
        return None, "stdout is not UTF-8"
    return RawStdout(buffer), None


def _flush_stdout(raw: Any) -> None:
    """After a core run: stdout flushed, quietly when its reader went away."""
    if raw is not None and not raw.broken:
        try:
            sys.stdout.flush()
        except BrokenPipeError:
            from mbmon.hub import _quiet_stdout

            _quiet_stdout()


def _log_opener(paths: list[str], args: argparse.Namespace, view: Any) -> Any:
    """Opens ``-w``'s one MCAP log (the core calls it once nothing declined, so a
    declined input never touches the file), as the Python pipeline opens it."""

    def open_log() -> Any:
        from mbmon.commands.common import open_logs

        return open_logs(args.write, log_context(args, paths, view, None), args)[0]

    return open_log


def log_context(args: argparse.Namespace, names: list[str], view: Any, annotator: Any) -> Any:
    """What the ``-w`` logs store besides the records (view, the inputs' names, settings)."""
    from mbmon.sinks.base import SinkContext

    return SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=" ".join(names),
        profiles=profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=args.timeout,
        baud=args.baud,
    )
