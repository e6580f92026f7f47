"""Command-line entry point: argument parsing and wiring only.

Every observing command ends in the same loop: a source yields chunks and
events, the :class:`~mbmon.pipeline.Pipeline` turns them into records, and the
records go to the console and to every ``-w`` sink.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import signal
import sys
from collections.abc import Callable, Iterable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from mbmon import __version__

EXIT_OK = 0
EXIT_BAD_INPUT = 1
EXIT_USAGE = 2

_READ_EPILOG = """\
examples:
  mbmon read captures/hrss_ptp.pcap
      print every Modbus ADU as the robot's Modbus Monitor shows it
  mbmon read plant.pcapng --port 1502 --json > frames.jsonl
      Modbus/TCP on a non-standard port, one JSON object per line
  mbmon read cell.pcap --robot 192.168.0.10 --profile hrss
      label lines from the robot's point of view and add HRSS meaning
  mbmon read bus.pcap --rtu-port 4001          RTU frames carried in TCP/UDP port 4001
  mbmon read --rtu-raw bus.bin                 a raw byte dump of an RS485 bus
  mbmon read cell.pcap -w cell.mcap            also record an MCAP log (Foxglove)

output lines: TIME  LABEL  [uUNIT tTID]  FUNCTION-CODE + DATA (hex)  | meaning
exit status: 0 ok, 1 bad or damaged input (everything before the damage is printed), 2 usage
"""

_DECODE_EPILOG = """\
examples:
  mbmon decode 02 01 2C 00 05                 a PDU as the manual prints it (query)
  mbmon decode --response 02 01 13            the same PDU read as a response
  mbmon decode 01 03 00 00 00 0A C5 CD        an RTU ADU (recognised by its CRC)
  mbmon decode 00 01 00 00 00 06 01 03 00 00 00 01   a Modbus/TCP ADU (MBAP header)
  mbmon decode --profile hrss 10 00 C9 00 03 06 00 6F 00 DE 01 4D
"""


class UsageError(Exception):
    """Bad command-line values; printed as ``mbmon: error: ...`` with exit status 2."""


# --------------------------------------------------------------------------- parser


def _port(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 < value < 65536:
        raise argparse.ArgumentTypeError(f"port out of range 1..65535: {value}")
    return value


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {value}")
    return value


def add_view_options(parser: argparse.ArgumentParser) -> None:
    """Options that decide how records are labelled and annotated (shared by observing commands)."""
    group = parser.add_argument_group("labels and meaning")
    group.add_argument(
        "--robot",
        metavar="HOST[:PORT]",
        help="the robot's endpoint: print the robot's own Modbus Monitor labels "
        '("Receive from client", "Send to server", ...); for RTU give the bus name',
    )
    group.add_argument(
        "--robot-client",
        action="store_true",
        help="on an RTU bus, the robot named by --robot is the master (client)",
    )
    group.add_argument(
        "--profile",
        action="append",
        default=[],
        metavar="SPEC",
        help="device profile for annotations: NAME or FILE.toml for all servers, "
        "HOST[:PORT]=NAME or unit:N=NAME for one (repeatable; built-in: hrss, xeg)",
    )


def add_output_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("output")
    group.add_argument(
        "--json", action="store_true", help="one JSON object per line (docs/json.md)"
    )
    group.add_argument(
        "-w",
        "--write",
        action="append",
        default=[],
        metavar="FILE",
        help="also write records to FILE; format by suffix: .mcap .jsonl .csv .txt .pcap "
        "(repeatable)",
    )
    group.add_argument(
        "-q", "--quiet", action="store_true", help="print nothing to stdout (use with -w)"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mbmon",
        description="Modbus RTU/TCP analyzer and monitor for HIWIN robot cells: shows what "
        "crosses the wire between a PLC and a robot, and what it means.",
        epilog="Run 'mbmon COMMAND --help' for the options and examples of each command.",
    )
    parser.add_argument("--version", action="version", version=f"mbmon {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    read = sub.add_parser(
        "read",
        help="decode a capture file (pcap/pcapng) or a raw RTU bus dump",
        description="Decode every Modbus ADU in a capture file and print it as the robot's "
        "Modbus Monitor (manual Table 57) shows it, with its meaning.",
        epilog=_READ_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    read.add_argument(
        "file", nargs="?", metavar="FILE", help="pcap or pcapng file (gzip too; - for stdin)"
    )
    src = read.add_argument_group("input")
    src.add_argument(
        "--port",
        action="append",
        type=_port,
        default=[],
        metavar="N",
        help="Modbus/TCP (and Modbus/UDP) server port, besides 502 (repeatable)",
    )
    src.add_argument(
        "--rtu-port",
        action="append",
        type=_port,
        default=[],
        metavar="N",
        help="TCP/UDP port carrying RTU ADUs with CRC, as some gateways do (repeatable)",
    )
    src.add_argument(
        "--rtu-raw",
        metavar="FILE",
        help="read FILE as a raw byte dump of an RS485 bus (RTU, both directions, no timing)",
    )
    src.add_argument(
        "--timeout",
        type=_positive,
        default=1.0,
        metavar="S",
        help="report a request unanswered after S seconds of capture time (default 1.0)",
    )
    src.add_argument(
        "--baud", type=int, metavar="N", help="RTU baud rate (silence gaps become health hints)"
    )
    add_view_options(read)
    add_output_options(read)
    read.set_defaults(func=run_read)

    decode = sub.add_parser(
        "decode",
        help="decode one frame typed by hand (hex)",
        description="Decode one Modbus frame given as hex bytes, as the manual prints them. "
        "Without --rtu/--tcp/--pdu the framing is guessed: a valid CRC means RTU, a "
        "consistent MBAP header means TCP, anything else is a bare PDU.",
        epilog=_DECODE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    decode.add_argument("hex", nargs="+", metavar="HEX", help="bytes, e.g. 02 01 2C 00 05")
    mode = decode.add_mutually_exclusive_group()
    mode.add_argument("--rtu", dest="mode", action="store_const", const="rtu", help="RTU ADU")
    mode.add_argument("--tcp", dest="mode", action="store_const", const="tcp", help="MBAP ADU")
    mode.add_argument("--pdu", dest="mode", action="store_const", const="pdu", help="bare PDU")
    decode.add_argument(
        "--response", action="store_true", help="read the PDU as a response (default: request)"
    )
    decode.add_argument("--json", action="store_true", help="print the decoded fields as JSON")
    decode.add_argument(
        "--profile", action="append", default=[], metavar="SPEC", help="annotate with a profile"
    )
    decode.set_defaults(func=run_decode)

    try:
        from mbmon import logcmds
    except ImportError:  # the log commands are optional until they exist
        logcmds = None  # type: ignore[assignment]
    if logcmds is not None:
        logcmds.add_subcommands(sub)
    import importlib

    from mbmon.commands import COMMANDS

    for name in COMMANDS:
        importlib.import_module(f"mbmon.commands.{name}").register(sub)
    return parser


# --------------------------------------------------------------------------- shared helpers


def _install_signal_handlers() -> None:
    """SIGTERM ends the run like Ctrl-C does, so every sink's close() runs."""

    def _terminate(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, _terminate)


def make_annotator(specs: list[str]) -> Any:
    """The annotator for ``--profile`` values (``None`` without); bad specs are usage errors."""
    from mbmon.semantics.annotate import annotator_for
    from mbmon.semantics.profile import ProfileError

    try:
        return annotator_for(specs)
    except ProfileError as exc:
        raise UsageError(str(exc)) from None


def _profile_sources(annotator: Any) -> list[tuple[str, str]]:
    if annotator is None:
        return []
    binding = getattr(annotator, "binding", None)
    sources = getattr(binding, "sources", None)
    return list(sources()) if callable(sources) else []


class _Progress:
    """A rich progress bar on stderr for long files, only when stderr is a terminal."""

    MIN_BYTES = 4 << 20  # about a second of reading

    def __init__(self, label: str, enabled: bool):
        self._bar: Any = None
        self._task: Any = None
        self._label = label
        self._enabled = enabled

    def __call__(self, done: int, total: int) -> None:
        if not self._enabled or total < self.MIN_BYTES:
            return
        if self._bar is None:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                DownloadColumn,
                Progress,
                TextColumn,
                TimeRemainingColumn,
            )

            self._bar = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                DownloadColumn(),
                TimeRemainingColumn(),
                console=Console(stderr=True),
                transient=True,
                # records go to stdout, the bar to stderr: rich must not take stdout
                redirect_stdout=False,
                redirect_stderr=False,
            )
            self._bar.start()
            self._task = self._bar.add_task(self._label, total=total)
        self._bar.update(self._task, completed=done)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()


# --------------------------------------------------------------------------- read


def _fast_lane(args: argparse.Namespace, pipeline: Any, view: Any, path: str) -> Any:
    """The fused reader (:mod:`mbmon.fastlane`) when it gives the same output faster:
    a capture file to ``--json`` on a UTF-8 stdout, no ``-w``, no ``--profile``."""
    from mbmon import fastlane
    from mbmon.sinks.console import utf8_buffer

    if (
        not args.json
        or args.quiet
        or args.write
        or pipeline.annotator is not None
        or not fastlane.enabled()
        or not Path(path).is_file()
    ):
        return None
    buffer = utf8_buffer(sys.stdout)
    return fastlane.FastLane(pipeline, view, buffer.write) if buffer is not None else None


def run_read(args: argparse.Namespace) -> int:
    from mbmon.format import View
    from mbmon.hub import Hub
    from mbmon.pipeline import Pipeline, PipelineConfig
    from mbmon.sinks.base import SinkContext, SinkError, open_sink
    from mbmon.sinks.console import ConsoleListener

    if args.rtu_raw and args.file:
        raise UsageError("give either FILE or --rtu-raw FILE, not both")
    if not args.rtu_raw and not args.file:
        raise UsageError("read needs a FILE (pcap/pcapng) or --rtu-raw FILE")
    view = View(robot=args.robot, robot_is_client=args.robot_client)
    annotator = make_annotator(args.profile)
    pipeline = Pipeline(annotator, PipelineConfig(timeout=args.timeout, baudrate=args.baud))
    path = args.rtu_raw or args.file
    if path == "-":
        path = "/dev/stdin"  # a pipe: the readers never seek
    progress = _Progress(f"reading {Path(path).name}", sys.stderr.isatty())
    lane = None

    if args.rtu_raw:
        from mbmon.sources.rawfile import read_rtu_raw

        if not Path(path).is_file():
            print(f"mbmon: {path}: no such file", file=sys.stderr)
            return EXIT_BAD_INPUT
        items: Iterable[Any] = read_rtu_raw(path)
    else:
        from mbmon.sources.pcapfile import CaptureConfig, CaptureError, read_capture

        config = CaptureConfig(
            tcp_ports=frozenset({502, *args.port}), rtu_ports=frozenset(args.rtu_port)
        )
        lane = _fast_lane(args, pipeline, view, path)
        try:
            items = read_capture(
                path, config, progress=progress, lane=lane.bind if lane is not None else None
            )
            first = next(iter_items := iter(items), None)
        except CaptureError as exc:
            print(f"mbmon: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        items = itertools.chain(() if first is None else (first,), iter_items)

    ctx = SinkContext(
        view=view,
        command_line=["mbmon", *sys.argv[1:]],
        source=str(path),
        profiles=_profile_sources(annotator),
        profile_specs=list(args.profile),
        timeout=args.timeout,
        baud=args.baud,
    )
    hub = Hub(pipeline)
    with ExitStack() as stack:
        stack.callback(hub.close)
        stack.callback(progress.close)
        if lane is not None:
            hub.add_listener(_LaneOutput(lane))
        elif not args.quiet:
            live = not Path(path).is_file()  # stdin or a FIFO: print as it comes
            hub.add_listener(ConsoleListener(sys.stdout, view, as_json=args.json, live=live))
        for target in args.write:
            try:
                hub.add_listener(open_sink(target, ctx))
            except SinkError as exc:
                print(f"mbmon: {exc}", file=sys.stderr)
                return EXIT_BAD_INPUT
        hub.run_items(items)
    if hub.errors:
        print(f"mbmon: {hub.errors[-1]}", file=sys.stderr)
        return EXIT_BAD_INPUT
    if any(why != "broken pipe" for _name, why in hub.failures):
        return EXIT_BAD_INPUT
    return EXIT_OK


class _LaneOutput:
    """The fused reader's output as a listener: records the general flow made
    become its JSON lines, written in blocks."""

    name = "stdout"

    def __init__(self, lane: Any) -> None:
        self.lane = lane

    def on_records(self, records: list[Any]) -> None:
        self.lane.records(records)
        self.lane.flush(_LANE_BLOCK)

    def close(self) -> None:
        self.lane.flush(0)
        sys.stdout.flush()


_LANE_BLOCK = 512


# --------------------------------------------------------------------------- decode


def _parse_hex(words: list[str]) -> bytes:
    text = " ".join(words).replace(",", " ").replace(":", " ")
    tokens = [t[2:] if t.lower().startswith("0x") else t for t in text.split()]
    joined = "".join(t if len(t) % 2 == 0 or len(tokens) == 1 else t.zfill(2) for t in tokens)
    try:
        data = bytes.fromhex(joined)
    except ValueError:
        raise UsageError(f"not hex bytes: {' '.join(words)!r}") from None
    if not data:
        raise UsageError("no bytes given")
    return data


def run_decode(args: argparse.Namespace) -> int:
    from mbmon.format import View, generic_note, monitor_hex, record_to_json
    from mbmon.model import (
        Direction,
        Frame,
        Kind,
        Record,
        RecordKind,
        Stream,
        Transaction,
        Transport,
        TxStatus,
    )
    from mbmon.protocol.crc import check_crc
    from mbmon.protocol.pdu import decode_pdu

    data = _parse_hex(args.hex)
    mode = args.mode
    if mode is None:
        if len(data) >= 4 and check_crc(data):
            mode = "rtu"
        elif len(data) >= 8 and data[2:4] == b"\0\0" and int.from_bytes(data[4:6]) == len(data) - 6:
            mode = "tcp"
        else:
            mode = "pdu"
    unit: int | None = None
    tid: int | None = None
    crc_ok: bool | None = None
    if mode == "rtu":
        if len(data) < 4:
            raise UsageError("an RTU ADU needs at least 4 bytes (unit, function code, CRC)")
        unit, body, crc_ok = data[0], data[1:-2], check_crc(data)
    elif mode == "tcp":
        if len(data) < 8:
            raise UsageError("a Modbus/TCP ADU needs at least 8 bytes (7-byte MBAP header + fc)")
        tid, unit, body = int.from_bytes(data[0:2]), data[6], data[7:]
        length = int.from_bytes(data[4:6])
        if length != len(data) - 6:
            print(
                f"mbmon: warning: MBAP length field says {length}, {len(data) - 6} bytes follow",
                file=sys.stderr,
            )
    else:
        body = data
    response = args.response or bool(body and body[0] & 0x80)
    pdu = decode_pdu(body, response)
    transport = {"rtu": Transport.RTU, "tcp": Transport.TCP}.get(mode, Transport.TCP)
    stream = Stream(0, transport, "client", "server")
    direction = Direction.S2C if response else Direction.C2S
    frame = Frame(0.0, stream, direction, unit if unit is not None else 0, tid, pdu, data, crc_ok)
    notes: tuple[str, ...] = ()
    annotator = make_annotator(args.profile)
    if annotator is not None:
        if response:
            tx = Transaction(0.0, TxStatus.UNSOLICITED, None, frame)
        else:
            tx = Transaction(0.0, TxStatus.PENDING, frame, None)
        notes = annotator.annotate(tx).notes
    kind = {Kind.REQUEST: RecordKind.REQUEST, Kind.RESPONSE: RecordKind.RESPONSE}.get(
        pdu.kind, RecordKind.EXCEPTION
    )
    record = Record(0, 0.0, kind, stream, frame=frame, notes=notes)
    if args.json:
        obj = record_to_json(record, View())
        obj["framing"] = mode
        for key in ("index", "time", "stream", "src", "dst", "line", "request_index"):
            obj.pop(key, None)
        print(json.dumps(obj, ensure_ascii=False))
        return EXIT_OK
    print(monitor_hex(pdu.raw))
    framing = {"rtu": "RTU ADU", "tcp": "Modbus/TCP ADU", "pdu": "PDU"}[mode]
    details = [f"framing: {framing}"]
    if unit is not None:
        details.append(f"unit: {unit}")
    if tid is not None:
        details.append(f"transaction id: {tid}")
    if crc_ok is not None:
        details.append(f"CRC: {'ok' if crc_ok else 'BAD'}")
    details.append(f"kind: {pdu.kind.value}")
    details.append(f"meaning: {generic_note(pdu)}")
    for name in ("address", "count", "byte_count", "exception_code"):
        value = getattr(pdu, name)
        if value is not None:
            details.append(f"{name.replace('_', ' ')}: {value}")
    if pdu.values is not None:
        details.append("values: " + ", ".join(str(v) for v in pdu.values))
    for name, value in pdu.fields.items():
        shown = value.hex(" ").upper() if isinstance(value, bytes) else value
        details.append(f"{name.replace('_', ' ')}: {shown}")
    if pdu.malformed:
        details.append(f"malformed: {pdu.malformed}")
    details.extend(f"note: {n}" for n in notes)
    print("\n".join("  " + d for d in details))
    return EXIT_OK


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] | None = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return EXIT_USAGE
    from mbmon.sinks.base import SinkError

    _install_signal_handlers()
    if hasattr(sys.stdout, "reconfigure"):
        # a terminal that cannot show "→" or "°" gets \u2192 escapes (valid inside JSON
        # strings too) instead of a traceback
        sys.stdout.reconfigure(errors="backslashreplace")
    try:
        return func(args)
    except UsageError as exc:
        parser.exit(EXIT_USAGE, f"mbmon: error: {exc}\n")
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # stdout closed early (e.g. `mbmon read big.pcap | head`): stop quietly.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    except SinkError as exc:  # an output failed while running (disk full, ...)
        print(f"mbmon: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:  # stdout or an output file failed while running
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"mbmon: {where}{exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
