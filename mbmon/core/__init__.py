"""The compiled core and the one place that decides whether it runs.

The core (:mod:`mbmon.core._reader`, Cython, built by ``pip install .``) runs
``mbmon read`` on the cases it covers and writes the very bytes the reference
pipeline would; everything else it *declines before writing a byte* and the
reference pipeline (pure Python) runs instead. The decision is made in two
places, both here:

* by the options (:func:`decline_for_options`): anything but a read of capture
  files to the console (``--json``, ``-t``, ``--robot``, the filters and ``-c``
  allowed) and/or one MCAP log (``-w x.mcap``) is declined at once;
* by the input (:func:`read_files`): the core's first pass reads each whole
  capture and only decides; a decline there (a gap, noise, a link type it does
  not cover, ...) comes before any output. Only when nothing declined does the
  second pass write.

With a log, the writing pass makes its messages and hands them to the same
``McapSink`` the Python pipeline uses, opened only once the first pass accepted
the input (:func:`read_file`'s ``log``).

``MBMON_NO_EXTENSIONS=1`` (or an install without a compiler) means the core is
never used; :func:`status` says which core is active (``mbmon --version``).
docs/architecture.md lists what the core covers and declines.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import os
import stat
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, Literal

__all__ = [
    "CoreRun",
    "available",
    "decline_for_options",
    "decline_for_profile",
    "read_buffer",
    "read_file",
    "read_files",
    "status",
]

_reader: Any = None
_tried = False
#: why the compiled core cannot run at all (None: it can), once it was looked for
_UNAVAILABLE: str | None = None


def _load() -> str | None:
    """Import the extension on first need (a run the options decline never pays for it);
    why it is unavailable, or ``None``."""
    global _reader, _tried, _UNAVAILABLE
    if not _tried:
        _tried = True
        if os.environ.get("MBMON_NO_EXTENSIONS", "") not in ("", "0"):
            _UNAVAILABLE = "MBMON_NO_EXTENSIONS is set"
        else:
            try:
                _reader = importlib.import_module("mbmon.core._reader")
            except ImportError as exc:  # installed without a compiler, or not built in place
                _UNAVAILABLE = f"not built ({exc})"
    return _UNAVAILABLE


def available() -> bool:
    """Whether the compiled core can run in this process."""
    return _load() is None


def status() -> str:
    """Which core is active, for ``mbmon --version``."""
    why = _load()
    if why is None:
        return "core: compiled (Cython extension mbmon.core._reader)"
    return f"core: pure Python ({why})"


def decline_for_options(args: Any, *, live: bool, flt: Any) -> str | None:
    """Why the options alone keep ``read`` off the core, or ``None`` when they allow it."""
    checks = (
        (args.rtu_raw, "--rtu-raw (RTU)"),
        (args.rtu_port, "--rtu-port (RTU over TCP/UDP)"),
        (not _one_mcap_log(args.write), "-w other than one .mcap log"),
        (getattr(args, "trigger", None), "--trigger"),
        (getattr(args, "rotate", None), "--rotate"),
        # without --trigger, a window is a usage error the Python path reports
        (getattr(args, "before", None) not in (None, "30s"), "--before"),
        (getattr(args, "after", None) not in (None, "10s"), "--after"),
        (args.profile and args.write, "--profile with -w"),
        (live, "a pipe, FIFO or device as input"),
    )
    return first_decline(checks)


def first_decline(checks: Iterable[tuple[Any, str]]) -> str | None:
    """The first of ``checks`` (``(present, what)`` pairs of an entry's options) that
    keeps a run off the core, as a decline's words; else why the core is unavailable,
    or ``None``: the core takes the run."""
    for present, what in checks:
        if present:
            return f"{what} is not covered by the core"
    why = _load()
    return None if why is None else f"the compiled core is unavailable: {why}"


def _one_mcap_log(targets: Any) -> bool:
    """Whether ``-w`` asks for no log, or for one MCAP log (the one log the core writes)."""
    targets = list(targets or [])
    return not targets or (len(targets) == 1 and str(targets[0]).lower().endswith(".mcap"))


def decline_for_profile(annotator: Any) -> str | None:
    """Why the profiles ``--profile`` binds keep ``read`` off the core (a profile naming a
    device session that does not support the core), or ``None``.

    The core writes the notes of read requests and their answers from the profile's
    compiled register map (:mod:`mbmon.semantics.profile.compiled`), hands every other
    step to the annotator, and tells a session only what its
    :class:`~mbmon.semantics.session.CoreWatch` asks for; a session without that
    (:attr:`~mbmon.semantics.session.Session.core_ready`) is declined here."""
    if annotator is None:
        return None
    from mbmon.semantics.session import Session, UnknownSession, session_factory

    for profile in annotator.binding.profiles():
        if profile.session is None:
            continue
        try:
            factory = session_factory(profile.session)
        except UnknownSession as exc:
            return f"--profile {profile.name}: {exc}"
        ready = isinstance(factory, type) and issubclass(factory, Session) and factory.core_ready
        if not ready:
            return f"--profile {profile.name}: session {profile.session!r} has no core support"
    return None


@dataclass
class CoreRun:
    """What the core did: ``declined`` says why it did not run (nothing was written)."""

    declined: str | None = None
    counts: dict[str, Any] = field(default_factory=dict)
    #: a signal (``KeyboardInterrupt``) cut the writing pass short: the counts are so far's
    #: and the log was finished with what came before it
    interrupted: bool = False


def _regular_file(path: str) -> bool:
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def read_file(
    path: str,
    *,
    ports: frozenset[int],
    timeout: float,
    view: Any,
    as_json: bool,
    write: Any | None,
    progress: Any | None = None,
    detect: bool = False,
    log: Any | None = None,
    annotator: Any | None = None,
    flt: Any | None = None,
    count: int | None = None,
) -> CoreRun:
    """Run the core on the capture at ``path``: a deciding pass, then (unless it
    declined, and when ``write`` or ``log`` is given) a writing pass that hands its
    output, in blocks of about 1 MiB of UTF-8, to ``write`` (``None``: no console).
    ``log()`` opens the MCAP log (an ``McapSink``) once nothing declined: the writing
    pass makes its messages, and the log is closed (finished) whatever happens. The
    counts are the summary's.
    With ``detect`` (the reference's port detection is on) the first pass feeds the
    reference's port detector every TCP segment on other ports and declines when it
    finds Modbus there."""
    return read_files(
        [path],
        ports=ports,
        timeout=timeout,
        view=view,
        as_json=as_json,
        write=write,
        progress=[progress],
        detect=detect,
        log=log,
        annotator=annotator,
        flt=flt,
        count=count,
    )


def read_files(
    paths: list[str],
    *,
    ports: frozenset[int],
    timeout: float,
    view: Any,
    as_json: bool,
    write: Any | None,
    progress: list[Any] | None = None,
    detect: bool = False,
    log: Any | None = None,
    annotator: Any | None = None,
    flt: Any | None = None,
    count: int | None = None,
) -> CoreRun:
    """:func:`read_file` on several captures read one after another into one output,
    each as it is alone (the reference's ``hub.end_of_input`` between two: its
    connections end with it, its requests time out at its own end, the next one's
    clock starts again), with one record numbering and one stream id allocator
    (``progress``: one per path). A gzip-compressed capture is decompressed into
    memory first. Declined as a whole when any input is."""
    if _load() is not None:
        return CoreRun(declined=f"the compiled core is unavailable: {_UNAVAILABLE}")
    inputs = []
    for path in paths:
        why = _input_decline(path)
        if why is not None:
            return CoreRun(declined=why)
        inputs.append(functools.partial(_opened, path))
    return _read_inputs(
        inputs,
        ports=ports,
        timeout=timeout,
        view=view,
        as_json=as_json,
        write=write,
        progress=progress or [None] * len(paths),
        detect=detect,
        log=log,
        annotator=annotator,
        flt=flt,
        count=count,
    )


#: the first bytes of a gzip stream
GZIP_MAGIC = b"\x1f\x8b"


def _input_decline(path: str) -> str | None:
    """Why the capture at ``path`` cannot be read by the core at all, or ``None``."""
    if not _regular_file(path):
        return "not a regular file"
    try:
        if os.path.getsize(path) == 0:
            return "an empty file"
    except OSError as exc:
        return f"cannot be read ({exc.strerror or exc})"
    return None


@contextlib.contextmanager
def _opened(path: str) -> Iterator[tuple[Any, Any]]:
    """The bytes of the capture at ``path`` and its ``release(offset, length)`` (or
    ``None``): the file mapped, or a gzip-compressed file decompressed into memory.
    :class:`_NoInput` (a decline) when it cannot be."""
    import mmap

    with open(path, "rb") as f:
        if f.read(2) == GZIP_MAGIC:
            import gzip
            import zlib

            f.seek(0)
            try:
                data = gzip.GzipFile(fileobj=f, mode="rb").read()
            except (OSError, EOFError, zlib.error) as exc:
                raise _NoInput(f"a damaged gzip stream ({exc})") from None
            if not data:
                raise _NoInput("an empty gzip stream")
            yield data, None
            return
        try:
            mapped: Any = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except ValueError:  # an empty file cannot be mapped
            raise _NoInput("an empty file") from None
    try:
        view = memoryview(mapped)
        try:
            yield view, _releaser(mapped)
        finally:
            view.release()
    finally:
        mapped.close()


class _NoInput(Exception):
    """An input the core cannot read at all (the message says why): a decline."""


def read_buffer(
    data: Any,
    *,
    ports: frozenset[int],
    timeout: float,
    view: Any,
    as_json: bool,
    write: Any | None,
    release: Any | None = None,
    progress: Any | None = None,
    detect: bool = False,
    log: Any | None = None,
    annotator: Any | None = None,
    flt: Any | None = None,
    count: int | None = None,
) -> CoreRun:
    """:func:`read_file` on a capture already in memory (``data``: bytes or a buffer);
    ``progress(done, total)`` is called about once per MiB (each pass is half).
    ``flt`` (an active ``RecordFilter``) selects the lines ``write`` gets, ``count``
    (``-c``) ends the run after that many frames it lets through (the counts too)."""
    if _load() is not None:
        return CoreRun(declined=f"the compiled core is unavailable: {_UNAVAILABLE}")
    return _read_inputs(
        [lambda: contextlib.nullcontext((data, release))],
        ports=ports,
        timeout=timeout,
        view=view,
        as_json=as_json,
        write=write,
        progress=[progress],
        detect=detect,
        log=log,
        annotator=annotator,
        flt=flt,
        count=count,
    )


def _read_inputs(
    inputs: list[Any],
    *,
    ports: frozenset[int],
    timeout: float,
    view: Any,
    as_json: bool,
    write: Any | None,
    progress: list[Any],
    detect: bool,
    log: Any | None,
    annotator: Any | None,
    flt: Any | None,
    count: int | None,
) -> CoreRun:
    """The two passes over ``inputs`` (each a callable giving a context of ``(data,
    release)``): every input decided first (nothing written), then written in order
    by one writing pass."""
    firsts = []
    for opened, bar in zip(inputs, progress, strict=True):
        try:
            with opened() as (data, release):
                first = _reader._Pass(False, as_json, timeout, ports, view, None, detect)
                first.release = release
                first.progress = bar
                first.run(data)
        except (_reader.Declined, _NoInput) as exc:
            return CoreRun(declined=str(exc))
        firsts.append(first)
    if sum(first.frames for first in firsts) == 0:
        return CoreRun(declined="no Modbus frames (the reference reader gives the hints)")
    if flt is not None and not flt.active:
        flt = None
    if flt is not None or count is not None:
        _start_selection(firsts, flt, count, view, show=write is not None)
    elif write is None and log is None and len(firsts) == 1:
        return CoreRun(counts=_counts(firsts[0]))
    # the first pass fed port detection every other-port segment and found no Modbus
    # there: the writing pass need not look again
    # with ``annotator`` (``--profile``) the writing pass annotates; the first only decides
    second = _reader._Pass(True, as_json, timeout, ports, view, write, False, annotator)
    if len(firsts) > 1:
        second.stream_ids(_run_stream_ids(firsts))
    if flt is not None or count is not None:
        second.select(flt, count, write is not None)

    def run_all() -> None:
        """Every input through the writing pass (the same decisions as the first pass:
        it cannot decline), one after another; ``-c`` may end it early."""
        try:
            for k, (opened, bar) in enumerate(zip(inputs, progress, strict=True)):
                with opened() as (data, release):
                    if k:
                        second.next_input()
                    second.release = release
                    second.progress = bar
                    second.progress_base = len(data) // 2
                    second.run(data)
        except _reader.Enough:  # -c: the N-th frame was written (and flushed)
            pass

    if log is None:
        run_all()
        return CoreRun(counts=_counts(second))
    interrupted = _run_logged(second, run_all, log())
    return CoreRun(counts=_counts(second), interrupted=interrupted)


def _run_stream_ids(firsts: list[Any]) -> list[int]:
    """The run's stream ids of the writing pass's streams over several inputs, in the
    order it makes them: the reference opens every source before reading any, and a
    source's opening reads its first item, so the streams each input made up to its
    first item come first (input by input), then the rest of each input in turn."""
    made = [first.stream_count() for first in firsts]
    opened = [
        min(f.open_streams if f.open_streams >= 0 else n, n)
        for f, n in zip(firsts, made, strict=True)
    ]
    ids: list[int] = []
    first_ids, rest_ids = 0, sum(opened)
    for n, o in zip(made, opened, strict=True):
        ids += range(first_ids, first_ids + o)
        ids += range(rest_ids, rest_ids + n - o)
        first_ids += o
        rest_ids += n - o
    return ids


def _start_selection(
    firsts: list[Any], flt: Any, count: int | None, view: Any, *, show: bool
) -> None:
    """Where the reference's filter and time format start, from the first passes (one
    per input, in order): the filter's ``--since``/``--until`` are resolved at the first
    record it is asked about (the console's filter asks about every record; ``-c``'s
    budget, the first listener of each batch, only about frames); with ``--grep`` every
    line is formatted, the budget's first, so ``-t r``'s origin and the automatic
    date's first day are that record's too."""
    first = next((one for one in firsts if one.any_record), firsts[0])
    b1_frame = first.b1_frame_ts == first.b1_frame_ts  # not NaN: the first batch had a frame
    if count is not None and show:
        start = first.b1_frame_ts if b1_frame else first.rec0_ts
    elif count is not None:
        start = next((one.frame0_ts for one in firsts if one.any_frame), first.rec0_ts)
    else:
        start = first.rec0_ts
    if flt is None:
        return
    flt.start_at(start)
    tf = getattr(view, "time_format", None)
    if flt.grep is not None and count is not None and show and b1_frame and tf is not None:
        if tf.mode == "r" and tf.origin is None:
            tf.origin = start
        if tf.auto_date and not tf.date and tf._day is None:
            tf._day = tf._day_of(start)


def _run_logged(second: Any, run: Any, sink: Any) -> bool:
    """The writing pass (``run()``) with an MCAP log: its messages go to ``sink``, which
    is finished (summary, index, footer) however the pass ends; one cut short (a
    signal, a failing log) leaves the whole items before it in the log. True when a
    signal cut it short."""
    complete = interrupted = False
    try:
        sink.write_here()  # no writer thread waiting for the GIL the core holds
        second.log_to(sink)
        run()
        complete = True
    except KeyboardInterrupt:  # SIGINT/SIGTERM: the log is finished, the caller says so
        interrupted = True
    finally:
        try:
            second.finish_log(complete)
        finally:
            sink.close()
    return interrupted


def _releaser(mapped: Any) -> Any:
    """``release(offset, length)``: drop pages of the mapped capture already read from
    the process (they are read again from the file if ever needed), or ``None``."""
    import mmap

    advice = getattr(mmap, "MADV_DONTNEED", None)
    if advice is None or not hasattr(mapped, "madvise"):
        return None

    def release(offset: int, length: int) -> None:
        mapped.madvise(advice, offset, length)

    return release


def _counts(done: Any) -> dict[str, Any]:
    return {
        "requests": done.requests,
        "responses": done.responses,
        "exceptions": done.exceptions,
        "timeouts": done.timeouts,
        "unsolicited": done.unsolicited,
        "malformed": done.malformed,
        "max_stream": done.max_stream,
        "robot_seen": done.robot_seen,
        "first": done.first if done.any_record else None,
        "last": done.last if done.any_record else None,
        "events": dict(done.events),
        "commands": done.command_counts() if hasattr(done, "command_counts") else None,
        "noise_records": done.noise_records,
        "noise_bytes": done.noise_bytes,
    }


def fill_summary(summary: Any, counts: dict[str, Any]) -> None:
    """Put the core's counts into a :class:`~mbmon.sinks.summary.Summary`."""
    for name in ("requests", "responses", "exceptions", "timeouts", "unsolicited", "malformed"):
        setattr(summary, name, counts[name])
    summary.max_stream = counts["max_stream"]
    summary.robot_seen = counts.get("robot_seen", False)
    summary.first = counts["first"]
    summary.last = counts["last"]
    summary.events.update(counts["events"])
    summary.noise_records += counts.get("noise_records", 0)  # MBAP noise (no CRC errors)
    summary.noise_bytes += counts.get("noise_bytes", 0)
    if counts.get("commands") is not None:  # --profile: robot commands by outcome, warnings
        commands, warnings = counts["commands"]
        summary.commands.update(commands)
        summary.warnings += warnings


def _pdu_entry(data: bytes, response: bool, request: bytes | None = None) -> Any:
    """Test-only: the core's decode and generic note of one PDU (see tests/core)."""
    if _load() is not None:
        raise RuntimeError(status())
    return _reader._native_note(data, response, request)


# ------------------------------------------------------------------ RTU framing
# The compiled RTU framer (mbmon.core._rtu) is a module of its own, loaded on first
# need like the reader; it frames a stream exactly as the reference RtuDecoder does
# without a baud rate, and is not asked for the rest (the reference decoder frames it).

_rtu: Any = None
_rtu_tried = False
#: why the compiled RTU framer cannot run at all (None: it can), once it was looked for
_RTU_UNAVAILABLE: str | None = None


def _load_rtu() -> str | None:
    """Import the RTU framer on first need; why it is unavailable, or ``None``."""
    global _rtu, _rtu_tried, _RTU_UNAVAILABLE
    if not _rtu_tried:
        _rtu_tried = True
        if os.environ.get("MBMON_NO_EXTENSIONS", "") not in ("", "0"):
            _RTU_UNAVAILABLE = "MBMON_NO_EXTENSIONS is set"
        else:
            try:
                _rtu = importlib.import_module("mbmon.core._rtu")
            except ImportError as exc:  # installed without a compiler, or not built in place
                _RTU_UNAVAILABLE = f"not built ({exc})"
    return _RTU_UNAVAILABLE


def rtu_decline(baudrate: int | None) -> str | None:
    """Why an RTU stream is framed by the reference decoder rather than the compiled
    one, or ``None`` when the compiled framer covers it (no baud rate: the timing
    rules of a known line speed, silences and USB bursts, are the reference's)."""
    if baudrate is not None and baudrate > 0:
        return "a baud rate (the RTU timing rules) is not covered by the core"
    why = _load_rtu()
    return None if why is None else f"the compiled RTU framer is unavailable: {why}"


def rtu_decoder(
    stream: Any, direction: Any, *, baudrate: int | None = None, silence: float | None = None
) -> Any | None:
    """The compiled RTU framer of one stream (the reference ``RtuDecoder``'s API and
    output), or ``None`` when :func:`rtu_decline` gives a reason (build the reference
    decoder then)."""
    if rtu_decline(baudrate) is not None:
        return None
    return _rtu.RtuCore(stream, direction, baudrate, silence)


def rtu_status(baudrate: int | None) -> str:
    """Which decoder frames RTU streams with this baud rate, for ``--debug-core``."""
    why = rtu_decline(baudrate)
    if why is None:
        return "RTU framing: the compiled framer (mbmon.core._rtu)"
    return f"RTU framing: the reference decoder ({why})"


# ------------------------------------------------------------------ RTU reads
# ``read --rtu-raw FILE`` end to end on the core: the compiled framer's frames paired
# and written by the reader's RTU pass (``_RtuPass`` in _rtu_pass.pxi), which covers
# every byte a dump holds (frames of every code, noise, CRC errors, timeouts,
# unsolicited answers), so it needs no deciding pass: what it does not cover is
# declined by the options alone (:func:`decline_for_rtu`).


def decline_for_rtu(args: Any, *, live: bool, flt: Any, annotator: Any = None) -> str | None:
    """Why ``read --rtu-raw`` stays off the core, or ``None`` when the core reads the
    dump: every option :func:`decline_for_options` declines (but ``--rtu-raw`` itself),
    and for RTU also ``-w`` (the core's log is Modbus/TCP's) and ``--profile``.

    ``--baud`` is covered: a dump has no capture times (every read is stamped 0.0), so
    the reference's timing rules never fire (a silence is the time between two reads
    less their bytes' time on the wire, never above t3.5; no tick reaches t3.5 after
    time 0.0) and its decoder frames the dump as the framer without a baud rate does.
    ``-t`` is covered for the same reason: an untimed bus's lines say ``#N``."""
    import argparse

    plain = argparse.Namespace(**{**vars(args), "rtu_raw": None})
    why = decline_for_options(plain, live=live, flt=flt)
    if why is not None:
        return why
    checks = (
        (args.write, "-w with --rtu-raw"),
        (annotator is not None or args.profile, "--profile with --rtu-raw"),
    )
    for present, what in checks:
        if present:
            return f"{what} is not covered by the core"
    return rtu_decline(None)


def read_rtu_file(
    path: str,
    *,
    timeout: float,
    view: Any,
    as_json: bool,
    write: Any | None,
    read_size: int = 4096,
    flt: Any | None = None,
    count: int | None = None,
) -> CoreRun:
    """The raw RTU dump at ``path`` (a regular file) read by the core, in reads of
    ``read_size`` bytes as the reference's source reads it (``RawRtuSource.chunk_size``):
    its lines to ``write`` (``None``: count only, ``-q``), the counts of the summary
    (noise too). ``flt`` (a ``RecordFilter``) selects the lines ``write`` gets,
    ``count`` (``-c``) ends the run after that many frames it lets through (the counts
    too), as for a capture (:func:`read_buffer`)."""
    if _load() is not None:
        return CoreRun(declined=f"the compiled core is unavailable: {_UNAVAILABLE}")
    if not _regular_file(path):
        return CoreRun(declined="not a regular file")
    import mmap
    from pathlib import Path

    from mbmon.model import Stream, Transport

    name = Path(path).name
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:  # the lines name the bus: the reference's escaping rules
        return CoreRun(declined="a dump whose file name is not UTF-8")
    stream = Stream(0, Transport.RTU, name, name, timed=False)  # as read_rtu_raw makes it
    try:
        f = open(path, "rb")  # closed below; an error declines
    except OSError as exc:  # the reference pipeline says why, as for any input
        return CoreRun(declined=f"cannot open the dump ({exc.strerror or exc})")
    with f:
        try:
            mapped: Any = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except ValueError:  # an empty file cannot be mapped
            mapped = None
    if flt is not None and not flt.active:
        flt = None
    # -c counts the frames the filters let through also without lines (-q)
    emit = write is not None or count is not None
    done = _reader._RtuPass(emit, as_json, timeout, view, write, stream)
    if flt is not None or count is not None:
        done.select(flt, count, write is not None)
    try:
        done.run_rtu(b"" if mapped is None else mapped, read_size)
    except _reader.Enough:  # -c: the N-th frame was written (and flushed)
        pass
    finally:
        if mapped is not None:
            mapped.close()
    counts = _counts(done)
    counts["noise"] = (done.noise_records, done.noise_bytes, done.crc_errors)
    return CoreRun(counts=counts)


def fill_rtu_summary(summary: Any, counts: dict[str, Any]) -> None:
    """:func:`fill_summary` of an RTU read, and its noise runs, bytes and CRC errors."""
    fill_summary(summary, counts)
    summary.noise_records, summary.noise_bytes, summary.crc_errors = counts["noise"]


# ------------------------------------------------------------------ RTU bus captures
# A capture of RTU buses (pcap or pcapng whose records are link type 147, USER0)
# read by the reader's RTU pass (``_RtuPass.run_bus``): the records' bytes framed by
# the compiled framer at their capture times, paired and written as ``read --rtu-raw``
# writes a dump, but timed. A deciding pass first (a damaged container, another link
# type, more than 64 buses or no frame declines before a byte is written), then the
# writing pass.

#: the link type of an RTU bus's records (USER0)
LINKTYPE_RTU_BUS = 147


def bus_capture(path: str) -> bool:
    """Whether the capture at ``path`` (a regular file, gzip-compressed or not)
    describes an RTU bus first: a pcap of link type 147, or a pcapng whose first
    interface is; the run then goes to :func:`read_bus_file` (which declines what else
    it holds)."""
    if not _regular_file(path):
        return False
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
            if head[:2] == GZIP_MAGIC:  # its first bytes decompressed (a damaged one: no)
                import gzip
                import zlib

                f.seek(0)
                try:
                    head = gzip.GzipFile(fileobj=f, mode="rb").read(4096)
                except (OSError, EOFError, zlib.error):
                    return False
    except OSError:
        return False
    if len(head) < 24:
        return False
    order: Literal["little", "big"]
    for order in ("little", "big"):
        magic = int.from_bytes(head[:4], order)
        if magic in (0xA1B2C3D4, 0xA1B23C4D, 0xA1B2CD34):
            return int.from_bytes(head[20:24], order) & 0x0FFFFFFF == LINKTYPE_RTU_BUS
    if head[:4] != b"\x0a\x0d\x0d\x0a":
        return False
    order = "little" if head[8:12] == b"\x4d\x3c\x2b\x1a" else "big"
    pos = int.from_bytes(head[4:8], order)  # the section header's length: the next block
    if pos + 12 > len(head) or int.from_bytes(head[pos : pos + 4], order) != 1:
        return False
    return int.from_bytes(head[pos + 8 : pos + 10], order) == LINKTYPE_RTU_BUS


def decline_for_bus(args: Any, *, live: bool, flt: Any, annotator: Any = None) -> str | None:
    """Why ``read`` of a capture of an RTU bus stays off the core, or ``None``: every
    option :func:`decline_for_options` declines but ``--rtu-port`` (it names TCP and
    UDP ports: a record of another link type declines the capture anyway), and a
    baud rate (the reference's timing rules, which the bus's capture times make
    fire), ``-w`` and ``--profile``."""
    import argparse

    plain = argparse.Namespace(**{**vars(args), "rtu_port": None})
    checks = (
        (args.baud, "--baud on a captured RTU bus (the timing rules)"),
        (args.write, "-w with an RTU bus capture"),
        (annotator is not None or args.profile, "--profile with an RTU bus capture"),
    )
    return decline_for_options(plain, live=live, flt=flt) or first_decline(checks)


def read_bus_file(
    path: str,
    *,
    timeout: float,
    view: Any,
    as_json: bool,
    write: Any | None,
    flt: Any | None = None,
    count: int | None = None,
) -> CoreRun:
    """The capture of RTU buses at ``path`` (see :func:`bus_capture`) read by the core:
    a deciding pass, then (with ``write``, a filter or ``-c``) the writing pass; the
    counts of the summary (noise too), as :func:`read_rtu_file` gives them."""
    if _load() is not None:
        return CoreRun(declined=f"the compiled core is unavailable: {_UNAVAILABLE}")
    why = _input_decline(path)
    if why is not None:
        return CoreRun(declined=why)
    from pathlib import Path

    from mbmon.model import Stream, Transport

    name = Path(path).name  # the dissector's bus name
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return CoreRun(declined="a capture whose file name is not UTF-8 (it names the bus)")
    stream = Stream(0, Transport.RTU, name, name)  # as the dissector's first bus

    def bus_pass(emit: bool) -> Any:
        return _reader._RtuPass(emit, as_json, timeout, view, write if emit else None, stream)

    try:
        with _opened(path) as (data, _release):
            first = bus_pass(False)
            try:
                first.run_bus(data)
            except _reader.Declined as exc:
                return CoreRun(declined=str(exc))
            if first.frames == 0:
                return CoreRun(declined="no Modbus frames (the reference reader gives the hints)")
            if flt is not None and not flt.active:
                flt = None
            if flt is None and count is None and write is None:
                done = first
            else:
                if flt is not None or count is not None:
                    _start_selection([first], flt, count, view, show=write is not None)
                done = bus_pass(True)
                if flt is not None or count is not None:
                    done.select(flt, count, write is not None)
                try:
                    done.run_bus(data)
                except _reader.Enough:  # -c: the N-th frame was written (and flushed)
                    pass
    except _NoInput as exc:
        return CoreRun(declined=str(exc))
    counts = _counts(done)
    counts["noise"] = (done.noise_records, done.noise_bytes, done.crc_errors)
    return CoreRun(counts=counts)
