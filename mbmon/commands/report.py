"""``mbmon report``: the figures of a capture or a log, as tables or pictures (docs/report.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

EPILOG = """\
examples:
  mbmon report cell.mcap                     poll cycles, latency, faults, bus health as tables
  mbmon report cell.pcap -o report.html      the same with pictures, one self-contained page
  mbmon report cell.mcap --png figures/      the pictures as PNG files
  mbmon report plant.pcapng --port 1502 --baud 19200

pictures need matplotlib: pip install 'mbmon[report]'
exit status: 0 ok, 1 bad input or output, 2 usage
"""


def register(sub: Any) -> None:
    """Add ``report`` to the CLI's sub-parsers."""
    from mbmon.commands.common import add_port_options, positive, positive_int

    p = sub.add_parser(
        "report",
        help="poll cycles, latency, faults and bus health of a capture or log, with pictures",
        description="The figures of a run: per client and register block the poll cycle "
        "(period, jitter, missed cycles) and latency percentiles; every exception and "
        "timeout on a timeline; commands and outcomes; RTU bus health. Tables on the "
        "terminal; with -o an HTML page with pictures that opens offline.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("input", metavar="LOG|CAPTURE", help="an MCAP log of mbmon, or pcap/pcapng")
    p.add_argument("-o", "--output", metavar="FILE.html", help="write the report as HTML")
    p.add_argument("--png", metavar="DIR", help="write every picture as DIR/NAME.png")
    src = p.add_argument_group("capture input (ignored for a log: it knows its own)")
    add_port_options(src)
    src.add_argument("--timeout", type=positive, default=1.0, metavar="S",
                     help="a request is unanswered after S seconds (default 1.0)")  # fmt: skip
    src.add_argument("--baud", type=positive_int, metavar="N",
                     help="RTU baud rate: bus utilisation and gaps")  # fmt: skip
    src.add_argument("--profile", action="append", default=[], metavar="SPEC",
                     help="device profile (commands and their outcomes; e.g. hrss)")  # fmt: skip
    p.set_defaults(func=run)


def _log_objects(path: str) -> tuple[list[dict[str, Any]], int | None]:
    from mbmon.io.mcap.reader import McapLog
    from mbmon.io.replay import logged_records, recorded_options

    with McapLog(path) as log:
        baud = recorded_options(log).baud
        return [r.obj for r in logged_records(log) if r.obj is not None], baud


def _capture_objects(args: argparse.Namespace) -> list[dict[str, Any]]:
    from mbmon.commands.common import make_annotator
    from mbmon.format import View, record_to_json
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sources.pcapfile import CaptureConfig, read_capture

    config = CaptureConfig(
        tcp_ports=frozenset({502, *args.port}),
        rtu_ports=frozenset(args.rtu_port),
        detect=not args.no_detect,
    )
    pipeline = Pipeline(
        make_annotator(args.profile), PipelineConfig(timeout=args.timeout, baudrate=args.baud)
    )
    view = View()
    return [record_to_json(r, view) for r in pipeline.run(read_capture(args.input, config))]


def run(args: argparse.Namespace) -> int:
    """``mbmon report``: tables on stdout, or the HTML page / PNG files asked for."""
    from mbmon.analysis.report import MissingExtra, analyse, render_html, render_png, text_tables
    from mbmon.commands.common import EXIT_BAD_INPUT, UsageError, err, exit_status
    from mbmon.commands.read import MCAP_MAGIC

    path = Path(args.input)
    if not path.is_file():
        err(f"{path}: no such file")
        return EXIT_BAD_INPUT
    if args.output and Path(args.output).suffix.lower() not in (".html", ".htm"):
        raise UsageError(f"{args.output}: the report is HTML (-o FILE.html)")
    with open(path, "rb") as f:
        is_log = f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    try:
        if is_log:
            objs, baud = _log_objects(str(path))
            baud = args.baud or baud
        else:
            objs, baud = _capture_objects(args), args.baud
    except Exception as exc:  # a damaged or foreign file: one line, no traceback
        from mbmon.io.mcap.reader import LogError
        from mbmon.sources.pcapfile import CaptureError

        if isinstance(exc, LogError | CaptureError):
            err(str(exc))
            return EXIT_BAD_INPUT
        raise
    figures = analyse(objs, source=path.name, baud=baud)
    if not args.output and not args.png:
        print(text_tables(figures))
        return exit_status()
    try:
        pictures = render_png(figures)
    except MissingExtra as exc:
        err(str(exc))
        return EXIT_BAD_INPUT
    try:
        if args.png:
            folder = Path(args.png)
            folder.mkdir(parents=True, exist_ok=True)
            for name, _title, png in pictures:
                (folder / f"{name}.png").write_bytes(png)
        if args.output:
            Path(args.output).write_text(render_html(figures, pictures), encoding="utf-8")
    except OSError as exc:
        err(f"{exc.filename or args.output}: cannot write: {exc.strerror or exc}")
        return EXIT_BAD_INPUT
    where = " and ".join(x for x in (args.output, args.png) if x)
    print(f"mbmon: report of {path.name}: {len(pictures)} pictures in {where}", file=sys.stderr)
    return exit_status()
