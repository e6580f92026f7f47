"""``mbmon sniff`` is wiring: its options build a source of the contract and the
outputs in the one order (logs first, then the screen, then the summary; ``-c`` in
front of them all), and the source's open failure is one line before any output."""

from __future__ import annotations

import io
import threading
from contextlib import redirect_stderr
from pathlib import Path

from mbmon.cli import build_parser
from mbmon.commands.common import FrameBudget, Limited, view_and_filter
from mbmon.commands.sniff import _attach_outputs, _context, _open_source, _source
from mbmon.hub import Hub
from mbmon.pipeline import Pipeline
from mbmon.sinks.console import ConsoleListener
from mbmon.sinks.summary import Summary
from mbmon.sources.serialbus import SerialBusSource
from mbmon.sources.sniff import InterfaceSource


def parse(*argv: str):
    return build_parser().parse_args(["sniff", *argv])


def inner(listener: object) -> object:
    return listener.inner if isinstance(listener, Limited) else listener


def test_options_build_the_source() -> None:
    serial = _source(parse("--serial", "/dev/ttyX", "--serial", "/dev/ttyY", "--baud", "9600"))
    assert isinstance(serial, SerialBusSource)
    assert serial.name == "/dev/ttyX+/dev/ttyY" and serial.settings.baudrate == 9600
    net = _source(parse("lo", "--port", "1502"))
    assert isinstance(net, InterfaceSource)
    assert net.bpf == "tcp port 502 or udp port 502 or tcp port 1502 or udp port 1502"
    assert not net.config.detect  # a named port keeps the kernel filter narrow


def test_logs_come_before_the_screen_and_the_summary(tmp_path: Path) -> None:
    log = tmp_path / "run.jsonl"
    args = parse("--serial", "/dev/ttyX", "--plain", "-w", str(log))
    hub = Hub(Pipeline())
    view, flt = view_and_filter(args)
    source = _source(args)
    ctx = _context(args, source, view, None)
    wired = _attach_outputs(args, hub, source, ctx, flt, None, lambda: None)
    assert wired is not None
    kinds = [type(listener) for listener in hub.listeners]
    assert kinds[0].__name__.lower().startswith("jsonl"), kinds
    assert kinds[1:] == [ConsoleListener, Summary]
    hub.close()


def test_count_sits_in_front_of_every_output(tmp_path: Path) -> None:
    args = parse("--serial", "/dev/ttyX", "--plain", "-c", "3", "-w", str(tmp_path / "a.jsonl"))
    hub = Hub(Pipeline())
    view, flt = view_and_filter(args)
    source = _source(args)
    _attach_outputs(args, hub, source, _context(args, source, view, None), flt, None, lambda: None)
    first, *rest = hub.listeners
    assert isinstance(first, FrameBudget)
    assert all(isinstance(listener, Limited) for listener in rest)
    assert [type(inner(listener)) for listener in rest][1:] == [ConsoleListener, Summary]
    hub.close()


def test_count_ends_the_run_without_closing_figures() -> None:
    """The N-th frame ends the run: the hub is done, so run_sources feeds no closing
    STATS event after it (the logs end at the N-th frame)."""
    hub = Hub(Pipeline())
    stopped = threading.Event()

    def enough() -> None:
        stopped.set()
        hub.enough()

    budget = FrameBudget(1, enough)
    from mbmon.model import Chunk, Direction, Stream, Transport
    from mbmon.protocol.mbap import encode_adu
    from mbmon.protocol.pdu import encode_read_request

    hub.add_listener(budget)
    stream = Stream(0, Transport.TCP, "a:1", "b:502")
    hub.feed(Chunk(1.0, stream, Direction.C2S, encode_adu(1, 1, encode_read_request(3, 0, 1))))
    assert budget.done and stopped.is_set() and hub.done


def test_a_port_that_cannot_open_is_one_line_and_no_output(tmp_path: Path) -> None:
    args = parse("--serial", str(tmp_path / "ttyNONE"), "-w", str(tmp_path / "x.mcap"))
    err = io.StringIO()
    with redirect_stderr(err):
        assert _open_source(_source(args), Hub()) is False
    assert err.getvalue().startswith(f"mbmon: cannot open serial port {tmp_path / 'ttyNONE'}: ")
    assert err.getvalue().count("\n") == 1
    assert not (tmp_path / "x.mcap").exists()


def test_count_is_the_one_count_option() -> None:
    """sniff's ``-c`` is :func:`add_count_option`'s: same help, a count > 0 or exit 2."""
    from mbmon.commands.common import COUNT_HELP

    sniff = build_parser()._subparsers._group_actions[0].choices["sniff"]  # type: ignore[union-attr]
    count = sniff._option_string_actions["-c"]
    assert count.help == COUNT_HELP and count.dest == "count"
    err = io.StringIO()
    with redirect_stderr(err):
        try:
            parse("lo", "-c", "0")
        except SystemExit as exc:
            assert exc.code == 2
        else:
            raise AssertionError("-c 0 was accepted")
    assert "must be > 0: 0" in err.getvalue()


def test_serial_line_options_come_from_the_one_builder() -> None:
    """``--baud`` is a whole number > 0 checked by argparse (as proxy's and sim's);
    unset when not given, so an interface run can refuse it; 115200 8N1 by default."""
    args = parse("--serial", "/dev/ttyX")
    assert (args.baud, args.parity, args.stopbits, args.bytesize) == (None, "N", 1, 8)
    assert _source(args).settings.baudrate == 115200
    err = io.StringIO()
    for bad in (["--baud", "0"], ["--baud", "fast"], ["--parity", "X"], ["--bytesize", "9"]):
        with redirect_stderr(err):
            try:
                parse("--serial", "/dev/ttyX", *bad)
            except SystemExit as exc:
                assert exc.code == 2, bad
            else:
                raise AssertionError(f"{bad} was accepted")
    assert "must be > 0: 0" in err.getvalue() and "not a whole number: 'fast'" in err.getvalue()


def test_sniff_proxy_and_sim_share_the_serial_line_options() -> None:
    """One home for ``--baud --parity --stopbits``: the same checks, choices and
    defaults in the three commands that open a serial line (only sniff's ``--baud``
    stays unset when not given: an interface run refuses it)."""
    from mbmon.commands.values import positive_int

    commands = build_parser()._subparsers._group_actions[0].choices  # type: ignore[union-attr]

    def line(name: str) -> list[tuple[object, ...]]:
        actions = commands[name]._option_string_actions
        return [
            (flag, actions[flag].type, actions[flag].choices, actions[flag].metavar)
            for flag in ("--baud", "--parity", "--stopbits")
        ]

    assert line("sniff") == line("proxy") == line("sim")
    assert line("sniff")[0][1] is positive_int
    for name in ("proxy", "sim"):
        args = build_parser().parse_args([name])
        assert (args.baud, args.parity, args.stopbits) == (115200, "N", 1), name
