"""``read`` of a capture arriving through a pipe, a FIFO or stdin (``-``) on the core's
streaming entry (:class:`mbmon.core.live.PipeCore`) against the reference (forced
pure): the same stdout bytes, stderr and exit status, with real FIFOs fed by a
writer thread (whole, byte by byte, with pauses the hub's ticks fall into) and a
real ``subprocess`` stdin pipe.

The pauses matter: the reference ticks its hub every quarter second of wall time at
the capture's time while a pipe is quiet, and a tick reports requests whose timeout
the pipeline's per-chunk tick (every 0.1 s of capture time) had not reached yet; so
a paused pipe prints a timeout earlier than the same file read whole does.
"""

from __future__ import annotations

import gzip
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from core_diff import REAL, ROOT, require_core
from gen import (
    T0,
    adus,
    every_function_pair,
    noisy_stream,
    reordered_conversation,
    retransmission_and_overlap,
    split_at_every_byte,
    udp_exchange,
    write_conversation,
    write_frames,
)
from opts_diff import Run, read_run

from mbmon.io.pcap import TcpConversation
from mbmon.protocol.mbap import encode_adu
from mbmon.protocol.pdu import encode_read_request, encode_read_response

CAPTURES = sorted(ROOT.glob("captures/*.pcap"))
REALS = sorted(p for p in REAL.glob("*") if p.suffix in (".pcap", ".pcapng"))
CORE_RAN = "core: the compiled core read the input"


@contextmanager
def _fifo(tmp_path: Path, pieces: list[bytes | float]) -> Iterator[Path]:
    """A FIFO a writer thread fills with ``pieces``: bytes written as they are, a
    number a pause of that many seconds (the pipe stays open and quiet)."""
    path = tmp_path / "pipe" / "cap"  # one name for every run: lines may name it
    path.parent.mkdir(exist_ok=True)
    path.unlink(missing_ok=True)
    os.mkfifo(path)

    def write() -> None:
        with open(path, "wb", buffering=0) as f:
            for piece in pieces:
                if isinstance(piece, float):
                    _drained(f.fileno())  # the pause begins once the reader has it all
                    time.sleep(piece)
                else:
                    try:
                        f.write(piece)
                    except BrokenPipeError:
                        return

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    try:
        yield path
    finally:
        writer.join(timeout=30)


def _drained(fd: int) -> None:
    """Wait until the reader took every byte written to the pipe ``fd`` (Linux answers
    FIONREAD on either end of a pipe)."""
    import fcntl
    import struct
    import termios

    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        left = struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
        if not left:
            return
        time.sleep(0.01)


def _both(tmp_path: Path, pieces: list[bytes | float], *opts: str) -> tuple[Run, Run]:
    """The same pieces through a FIFO read by the core, then forced pure."""
    with _fifo(tmp_path, pieces) as fifo:
        fast = read_run([fifo, *opts])
    with _fifo(tmp_path, pieces) as fifo:
        pure = read_run([fifo, *opts], pure=True)
    return fast, pure


def _assert_same(fast: Run, pure: Run, *, handed: str | None = None) -> None:
    """Byte for byte the same; the core read the input (``handed``: then handed the
    run to the reference for that reason)."""
    said = " ".join(fast.core)
    if handed is None:
        assert fast.core == [CORE_RAN], said
    else:
        assert said.startswith(CORE_RAN + ", then the Python pipeline (") and handed in said, said
    assert fast.out.splitlines() == pure.out.splitlines()
    assert fast.out == pure.out
    assert fast.err == pure.err
    assert fast.status == pure.status


@pytest.mark.parametrize(
    "opts", [(), ("--json",), ("-t", "r"), ("-q",), ("--robot", "127.0.0.1", "-t", "ud")], ids=str
)
def test_every_project_capture_through_a_fifo(tmp_path: Path, opts: tuple[str, ...]) -> None:
    require_core()
    for path in CAPTURES:
        fast, pure = _both(tmp_path, [path.read_bytes()], *opts)
        rtu = path.name in ("hrss_rtu.pcap", "sim_rtu.pcap")  # USER0: the reference's
        _assert_same(fast, pure, handed="link type 147" if rtu else None)


def test_every_public_capture_through_a_fifo(tmp_path: Path) -> None:
    require_core()
    if not REALS:
        pytest.skip(f"no public captures at {REAL}")
    for path in REALS:
        fast, pure = _both(tmp_path, [path.read_bytes()])
        _assert_same(fast, pure)


def test_byte_by_byte_and_gzip_and_pcapng(tmp_path: Path) -> None:
    """A capture arriving one byte per write, gzip-compressed on the pipe, and pcapng."""
    require_core()
    data = (ROOT / "captures" / "sim_functions.pcap").read_bytes()
    _assert_same(*_both(tmp_path, [data[i : i + 1] for i in range(len(data))]))
    _assert_same(*_both(tmp_path, [gzip.compress(data)], "--json"))
    ng = write_conversation(tmp_path / "ng.pcapng", adus(every_function_pair()), pcapng=True)
    _assert_same(*_both(tmp_path, [ng.read_bytes()]))


def _late_timeout(folder: Path) -> tuple[bytes, int]:
    """A request (t=0) left unanswered while another connection polls: the pipeline's
    per-chunk tick runs at 0.95 s (next due at 1.05 s), so the request's timeout (1 s)
    is reported by the chunk at 1.2 s, after the polls at 1.03 and 1.04 s; a hub tick
    in a pause after the poll at 1.02 s reports it before them. The capture, and the
    byte offset after that poll (where the pause goes)."""
    lost = TcpConversation("10.0.0.1:40000", "10.0.0.2:502")
    poll = TcpConversation("10.0.0.3:40001", "10.0.0.2:502")
    frames = [(T0 - 0.01, f) for f in lost.open() + poll.open()]
    frames.append((T0, lost.send(True, encode_adu(1, 1, encode_read_request(3, 0, 2)))))
    cut = 0
    for tid, t in enumerate((0.02, 0.5, 0.95, 1.02, 1.03, 1.04, 1.2), 2):
        frames.append((T0 + t, poll.send(True, encode_adu(tid, 1, encode_read_request(4, 0, 1)))))
        answer = encode_adu(tid, 1, encode_read_response(4, [tid]))
        frames.append((T0 + t + 0.001, poll.send(False, answer)))
        if t == 1.02:
            cut = len(frames)
    data = write_frames(folder / "late.pcap", frames).read_bytes()
    offset = 24
    for _ in range(cut):  # past the cut-th record
        offset += 16 + int.from_bytes(data[offset + 8 : offset + 12], "little")
    return data, offset


@pytest.mark.parametrize("opts", [(), ("--json",)], ids=str)
def test_a_quiet_pipe_reports_a_timeout_at_the_hubs_tick(
    tmp_path: Path, opts: tuple[str, ...]
) -> None:
    require_core()
    data, cut = _late_timeout(tmp_path)
    fast, pure = _both(tmp_path, [data[:cut], 0.6, data[cut:]], *opts)
    _assert_same(fast, pure)
    whole = tmp_path / "whole.pcap"
    whole.write_bytes(data)
    from_file = read_run([whole, *opts])
    # the pause moved the timeout before the polls after it: not the file's order
    lines, file_lines = fast.out.splitlines(), from_file.out.splitlines()
    assert len(lines) == len(file_lines) and lines != file_lines
    timeout = [n for n, line in enumerate(lines) if b"No response" in line or b'"timeout"' in line]
    in_file = (
        [n for n, line in enumerate(file_lines) if line == lines[timeout[0]]] if timeout else []
    )
    assert len(timeout) == 1 and (opts or in_file[0] > timeout[0])


def test_noise_and_a_pause_inside_an_adu(tmp_path: Path) -> None:
    """Noise and MBAP length 255 (the reference decoder inside the core), a pause with
    half an ADU held, then the rest."""
    require_core()
    for seed in range(2):
        path = write_conversation(tmp_path / f"noise{seed}.pcap", noisy_stream(seed), step=0.3)
        data = path.read_bytes()
        half = len(data) // 2
        _assert_same(*_both(tmp_path, [data[:half], 0.4, data[half:]]))


def test_generated_captures_through_a_fifo(tmp_path: Path) -> None:
    """Splits at every byte, retransmissions and overlaps, reordered and lost segments
    (holes the end gives up), Modbus/UDP."""
    require_core()
    paths = split_at_every_byte(tmp_path)[::3]
    paths.append(retransmission_and_overlap(tmp_path))
    paths += [reordered_conversation(tmp_path / f"r{seed}.pcap", seed) for seed in range(4)]
    paths.append(udp_exchange(tmp_path / "udp.pcap", adus(every_function_pair()[:8])))
    for path in paths:
        fast, pure = _both(tmp_path, [path.read_bytes()], "--json")
        assert fast.out == pure.out, path.name
        assert fast.err == pure.err and fast.status == pure.status, path.name
        assert fast.core[0].startswith(CORE_RAN), fast.core


def test_a_pipe_that_ends_mid_record(tmp_path: Path) -> None:
    """A capture cut inside a record (and inside a pcapng block): the lines before it,
    the end at the last good record's time, the ERROR line, exit status 1."""
    require_core()
    data = (ROOT / "captures" / "demo.pcap").read_bytes()
    ng = write_conversation(tmp_path / "cut.pcapng", adus(every_function_pair()), pcapng=True)
    at = 24  # the 40th record's header: its length garbled (corrupt), or cut inside
    for _ in range(40):
        at += 16 + int.from_bytes(data[at + 8 : at + 12], "little")
    corrupt = data[: at + 8] + (1 << 30).to_bytes(4, "little") + data[at + 12 :]
    cuts = (data[: len(data) - 30], data[: len(data) // 2 + 7], data[: at + 9], corrupt)
    for cut in (*cuts, ng.read_bytes()[:-9]):
        fast, pure = _both(tmp_path, [cut])
        _assert_same(fast, pure, handed="the capture ended early")
        assert fast.status == 1 and (": truncated " in fast.err or ": corrupt " in fast.err)


def test_port_detection_hands_over_at_the_promotion(tmp_path: Path) -> None:
    """Modbus on a port not named: the core covers the run until port detection
    promotes that connection, and the reference replays what the detector held."""
    require_core()
    from test_core_cli import _two_ports

    both = _two_ports(tmp_path / "both.pcap", 1502).read_bytes()
    fast, pure = _both(tmp_path, [both])
    _assert_same(fast, pure, handed="Modbus found by port detection on port 1502")
    assert "found Modbus/TCP on port 1502" in fast.err
    _assert_same(*_both(tmp_path, [both], "--no-detect"))


def test_what_the_pipe_entry_declines_says_why(tmp_path: Path) -> None:
    require_core()
    data = (ROOT / "captures" / "demo.pcap").read_bytes()
    log = tmp_path / "x.mcap"
    for opts, why in (
        (("-w", str(log)), "-w (logs) from a pipe"),
        (("--since", "1s", "-c", "3"), "--since/--until with -c from a pipe"),
        (("--grep", "read", "-c", "3"), "--grep with -c from a pipe"),
    ):
        fast, pure = _both(tmp_path, [data], *opts)
        assert fast.core == [
            f"core: declined ({why} is not covered by the core); the Python pipeline reads "
            "the input"
        ]
        assert fast.out == pure.out and fast.err == pure.err and fast.status == pure.status


def test_bad_input_on_a_pipe_is_one_line(tmp_path: Path) -> None:
    require_core()
    for pieces in ([b""], [b"not a capture at all"]):
        fast, pure = _both(tmp_path, pieces)
        assert fast.status == pure.status == 1
        assert fast.out == pure.out == b""
        assert fast.err == pure.err and fast.err.count("\n") == 1


def _mbmon(stdin: bytes, *args: str, pure: bool = False) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ)
    env.pop("MBMON_NO_EXTENSIONS", None)
    if pure:
        env["MBMON_NO_EXTENSIONS"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "mbmon", "read", "-", *args],
        input=stdin,
        capture_output=True,
        env=env,
        cwd=ROOT,
        timeout=120,
    )


def test_stdin_through_a_real_pipe() -> None:
    """``cat F | mbmon read -``: stdin as the process's pipe."""
    require_core()
    data = (ROOT / "captures" / "hrss_ptp.pcap").read_bytes()
    fast = _mbmon(data, "--debug-core", "--json")
    pure = _mbmon(data, "--json", pure=True)
    assert fast.returncode == pure.returncode == 0
    assert fast.stderr.splitlines()[0] == b"mbmon: " + CORE_RAN.encode()
    assert fast.stdout == pure.stdout and fast.stdout.count(b"\n") > 10
    assert fast.stderr.splitlines()[1:] == pure.stderr.splitlines()


def test_no_modbus_on_a_pipe_gives_the_busiest_ports(tmp_path: Path) -> None:
    """Traffic on other ports only (TCP over IPv4 and IPv6, UDP): the core counts the
    packets per port as the reference dissector does, for the summary's hint."""
    require_core()
    from gen import ipv6_segment

    web = TcpConversation("10.0.0.1:40000", "10.0.0.2:80")
    frames = web.open() + [web.send(c, b"GET / HTTP/1.0\r\n" * 3) for c in (True, False) * 4]
    six = TcpConversation("[2001:db8::1]:40000", "[2001:db8::2]:8080")
    frames += [ipv6_segment(six, c, 0x18, b"\x00\x01" * 9) for c in (True, False) * 3]
    records = [(T0 + n * 0.01, f) for n, f in enumerate(frames)]
    data = write_frames(tmp_path / "web.pcap", records).read_bytes()
    dns = udp_exchange(tmp_path / "dns.pcap", [(True, b"\x12\x34" * 9)] * 5, server="10.0.0.9:53")
    data += dns.read_bytes()[24:]  # its records after the others'
    for opts in ((), ("--no-detect",)):
        fast, pure = _both(tmp_path, [data], *opts)
        _assert_same(fast, pure)
        assert "tcp/8080 (6 packets)" in fast.err and "udp/53 (5 packets)" in fast.err
        assert ("tcp/80 (" in fast.err) == bool(opts)  # with detection: held, not counted


@pytest.mark.parametrize(
    "opts",
    [
        ("-c", "3"),
        ("-c", "40", "--json"),
        ("--fc", "3,4", "-c", "9", "-t", "r"),
        ("--unit", "1", "--address", "100-200"),
        ("--grep", "holding"),
        ("--where", "fc 3 or exception or timeout", "--json"),
        ("-q", "-c", "7"),
        ("--since", "+1s", "--fc", "4"),
        ("--since", "+250ms", "--until", "+1.5s", "-t", "r", "--json"),
        ("--until", "2023-11-14 22:13:20.3", "-t", "ud"),
    ],
    ids=str,
)
def test_filters_and_count_on_a_pipe(tmp_path: Path, opts: tuple[str, ...]) -> None:
    """The console behind the filters and ``-c`` (the N-th frame they let through ends
    the run), also when port detection hands the run over before or after the N-th;
    ``--since``/``--until`` from the first record, as the console's filter resolves them."""
    require_core()
    from test_core_cli import _two_ports

    both = _two_ports(tmp_path / "both.pcap", 1502).read_bytes()
    for data in [p.read_bytes() for p in CAPTURES[:3]] + [both]:
        fast, pure = _both(tmp_path, [data], *opts)
        assert fast.out == pure.out and fast.status == pure.status, opts
        if data is both and "-c" in opts:
            # the reference's pipe reader (a thread of its own) may or may not have
            # finished the capture when -c ends the run: "found ... on port 1502" is
            # said when it had (the core says it: its detector found it before the stop)
            assert _without_found(fast.err) == _without_found(pure.err)
            assert "-q" in opts or "found Modbus/TCP on port 1502" in fast.err
        else:
            assert fast.err == pure.err
        assert fast.core[0].startswith(CORE_RAN), fast.core


def _without_found(err: str) -> str:
    return "".join(ln for ln in err.splitlines(keepends=True) if "found Modbus/TCP" not in ln)


_SLOW_WRITER = """
import fcntl, struct, sys, termios, time
data = open(sys.argv[1], "rb").read()
cut = int(sys.argv[2])
sys.stdout.buffer.write(data[:cut]); sys.stdout.buffer.flush()
end = time.monotonic() + 60  # the pause begins once the reader (started with us) took it all
while time.monotonic() < end and struct.unpack(
        "i", fcntl.ioctl(1, termios.FIONREAD, b"\\0\\0\\0\\0"))[0]:
    time.sleep(0.01)
time.sleep(0.7)
sys.stdout.buffer.write(data[cut:]); sys.stdout.buffer.flush()
"""


def test_a_slow_writing_process_on_stdin(tmp_path: Path) -> None:
    """``writer | mbmon read -`` with a writer process that pauses where a timeout
    falls due: the same lines, the timeout where the pure run prints it."""
    require_core()
    _, cut = _late_timeout(tmp_path)
    path = tmp_path / "late.pcap"  # what _late_timeout wrote
    runs = []
    for pure in (False, True):
        env = dict(os.environ)
        env.pop("MBMON_NO_EXTENSIONS", None)
        if pure:
            env["MBMON_NO_EXTENSIONS"] = "1"
        writer = subprocess.Popen(
            [sys.executable, "-c", _SLOW_WRITER, str(path), str(cut)], stdout=subprocess.PIPE
        )
        reader = subprocess.run(
            [sys.executable, "-m", "mbmon", "read", "-", "--debug-core"],
            stdin=writer.stdout,
            capture_output=True,
            env=env,
            cwd=ROOT,
            timeout=120,
        )
        assert writer.stdout is not None
        writer.stdout.close()
        writer.wait(timeout=30)
        runs.append(reader)
    fast, pure = runs
    assert fast.stderr.splitlines()[0] == b"mbmon: " + CORE_RAN.encode()
    assert fast.returncode == pure.returncode == 0
    assert fast.stdout == pure.stdout
    assert fast.stderr.splitlines()[1:] == pure.stderr.splitlines()[1:]
    assert fast.stdout != read_run([path]).out  # the pause moved the timeout
