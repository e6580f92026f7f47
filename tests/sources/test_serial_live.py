"""`mbmon sniff --serial`: real pty pairs made by socat, a writer replaying RTU bus traffic.

The writer writes requests and responses of many function codes into one end of
a socat pty pair, back to back and with gaps, split into random small writes,
with noise bytes and a wrong-CRC frame among them; ``python -m mbmon sniff
--serial`` reads the other end. Every valid frame must come out, in order, and
the noise must be reported. Killing socat (the port disappears) must be
reported, and the sniffer must pick the port up again when socat returns.
"""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from mbmon.protocol.rtu import encode_rtu

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


class PtyPair:
    """``socat pty,link=A pty,link=B``: bytes written to A come out of B."""

    def __init__(self, a: Path, b: Path) -> None:
        self.a, self.b = a, b
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [
                "socat",
                f"pty,raw,echo=0,link={self.a}",
                f"pty,raw,echo=0,link={self.b}",
            ],
            stderr=subprocess.DEVNULL,
        )
        end = time.monotonic() + 5
        while not (self.a.exists() and self.b.exists()):
            assert time.monotonic() < end, "socat made no ptys"
            time.sleep(0.02)

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait()
            self.proc = None
        end = time.monotonic() + 5
        while self.a.exists() or self.b.exists():
            assert time.monotonic() < end, "socat left its links behind"
            time.sleep(0.02)


@pytest.fixture
def pty_pair(tmp_path: Path) -> Iterator[PtyPair]:
    pair = PtyPair(tmp_path / "ttyW", tmp_path / "ttyS")
    pair.start()
    try:
        yield pair
    finally:
        pair.stop()


def _adu(unit: int, pdu_hex: str) -> bytes:
    return encode_rtu(unit, bytes.fromhex(pdu_hex.replace(" ", "")))


#: (request, response) PDUs of many function codes, as a master and slaves exchange them.
_EXCHANGES: list[tuple[int, str, str | None]] = [
    (1, "03 0000 0002", "03 04 0001 0002"),
    (2, "01 0013 0013", "01 03 CD 6B 05"),
    (1, "02 00C4 0016", "02 03 AC DB 35"),
    (3, "04 0008 0001", "04 02 000A"),
    (1, "05 00AC FF00", "05 00AC FF00"),
    (1, "06 0001 0003", "06 0001 0003"),
    (4, "0F 0013 000A 02 CD 01", "0F 0013 000A"),
    (1, "10 0001 0002 04 000A 0102", "10 0001 0002"),
    (1, "17 0003 0006 000E 0003 06 00FF 00FF 00FF", "17 0C 00FE 0ACD 0001 0003 000D 00FF"),
    (1, "16 0004 00F2 0025", "16 0004 00F2 0025"),
    (5, "08 0000 A537", "08 0000 A537"),
    (1, "03 0100 0001", "83 02"),
    (0, "06 0001 0005", None),  # broadcast: no answer
    (1, "11", "11 04 01 FF 41 42"),
]


Piece = tuple[bytes, float, bool]  # bytes, pause after, write whole


def _traffic(seed: int = 11) -> tuple[list[Piece], list[str], int]:
    """The bus as a list of pieces, the expected frame PDUs in order (hex), and the
    number of noise bytes injected (wrong-CRC frame included). Round 0 is back to
    back; rounds 1 and 2 pause 0, 2 or 20 ms between exchanges, and round 1 also
    inside two requests."""
    rng = random.Random(seed)
    pieces: list[Piece] = []
    expected: list[str] = []
    noise = 0
    for round_ in range(3):
        for i, (unit, req, resp) in enumerate(_EXCHANGES):
            if round_ == 1 and i in (3, 9):
                junk = bytes([0x00, 0xFF, 0x00, 0x00][: 2 + i % 3])
                pieces.append((junk, 0.0, False))
                noise += len(junk)
            if round_ == 2 and i == 5:
                bad = bytearray(_adu(1, "03 0000 0001"))
                bad[-1] ^= 0x5A  # a wrong CRC
                pieces.append((bytes(bad), 0.0, False))
                noise += len(bad)
            gap = 0.0 if round_ == 0 else rng.choice((0.0, 0.002, 0.02))  # round 0: back to back
            frames = [_adu(unit, req)] + ([_adu(unit, resp)] if resp is not None else [])
            expected.append(req)
            if resp is not None:
                expected.append(resp)
            data = b"".join(frames)
            if round_ == 1 and i in (0, 10):
                # a 20 ms silence inside a request (03, and 08 whose length nothing
                # predicts): silence is a hint only, the frame still comes out whole
                pieces.append((data[:4], 0.02, False))
                data = data[4:]
            pieces.append((data, gap, False))
    return (
        pieces,
        [" ".join(f"{b:02X}" for b in bytes.fromhex(p.replace(" ", ""))) for p in expected],
        noise,
    )


def _write(path: Path, pieces: list[Piece], seed: int = 5) -> None:
    """Write the pieces in random small writes (1..9 bytes, sometimes 1 ms apart),
    or whole where asked, pausing where asked."""
    rng = random.Random(seed)
    fd = os.open(path, os.O_WRONLY | os.O_NOCTTY)
    try:
        for data, pause, whole in pieces:
            pos = 0
            while pos < len(data):
                n = len(data) if whole else rng.randint(1, 9)
                os.write(fd, data[pos : pos + n])
                pos += n
                if rng.random() < 0.1:
                    time.sleep(0.001)
            if pause:
                time.sleep(pause)
    finally:
        os.close(fd)


_STARTED: list[subprocess.Popen[bytes]] = []


@pytest.fixture(autouse=True)
def _no_leftover_sniffers() -> Iterator[None]:
    """A test that fails between starting a sniffer and stopping it leaves none running."""
    yield
    while _STARTED:
        proc = _STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait()


class SerialSniffer:
    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "sniff", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=_env(),
            cwd=REPO,
        )
        _STARTED.append(self.proc)
        self.out = b""
        self.err = b""
        self._until(self.proc.stderr, b"sniffing", 15)

    def _until(self, pipe: object, needle: bytes, timeout: float) -> None:
        import select

        attr = "err" if pipe is self.proc.stderr else "out"
        end = time.monotonic() + timeout
        while needle not in getattr(self, attr):
            left = end - time.monotonic()
            if left <= 0 or self.proc.poll() is not None:
                raise AssertionError(
                    f"{needle!r} not seen; out: {self.out.decode()} err: {self.err.decode()}"
                )
            ready, _, _ = select.select([pipe], [], [], min(left, 0.1))
            if ready:
                setattr(self, attr, getattr(self, attr) + os.read(pipe.fileno(), 65536))  # type: ignore[attr-defined]

    def stdout_until(self, needle: bytes, timeout: float = 5.0) -> None:
        self._until(self.proc.stdout, needle, timeout)

    def finish(self) -> tuple[str, str]:
        self.proc.send_signal(signal.SIGINT)
        out, err = self.proc.communicate(timeout=10)
        return (self.out + out).decode(), (self.err + err).decode()


def _records(stdout: str) -> list[dict[str, object]]:
    return [json.loads(line) for line in stdout.splitlines() if line.strip()]


def test_serial_sniffer_recovers_every_valid_frame_and_reports_noise(pty_pair: PtyPair):
    pieces, expected, noise = _traffic()
    sniffer = SerialSniffer("--serial", str(pty_pair.b), "--json", "--baud", "115200")
    _write(pty_pair.a, pieces)
    sniffer.stdout_until(b'"11 04 01 FF 41 42"', timeout=5)
    time.sleep(0.3)
    out, err = sniffer.finish()
    assert sniffer.proc.returncode == 0, err
    records = _records(out)
    frames = [r["pdu"] for r in records if r["kind"] in ("request", "response", "exception")]
    assert frames == expected
    noise_records = [r for r in records if r["kind"] == "noise"]
    assert sum(len(str(r["pdu"]).split()) for r in noise_records) == noise
    assert any("bad CRC" in str(r["line"]) for r in noise_records)
    stats = [r for r in records if r["kind"] == "event" and "Stats:" in str(r["line"])]
    assert stats and f"noise_bytes={noise}" in str(stats[-1]["line"])
    assert f"{len(expected)} frames" in err and f"{noise} noise bytes" in err
    assert "CRC failures" in err and "inter-frame gaps" in err


def test_serial_port_lost_is_reported_and_picked_up_again(pty_pair: PtyPair, tmp_path: Path):
    log = tmp_path / "bus.mcap"
    sniffer = SerialSniffer("--serial", str(pty_pair.b), "--plain", "-w", str(log))
    _write(pty_pair.a, [(_adu(1, "03 0000 0001") + _adu(1, "03 02 002A"), 0.0, False)])
    sniffer.stdout_until(b"03 02 00 2A")
    pty_pair.stop()  # the USB adapter is unplugged
    sniffer.stdout_until(b"lost", timeout=5)
    pty_pair.start()  # and plugged in again
    sniffer.stdout_until(b"is back", timeout=5)
    _write(pty_pair.a, [(_adu(1, "06 0001 0003") + _adu(1, "06 0001 0003"), 0.0, False)])
    sniffer.stdout_until(b"06 00 01 00 03  | Write Single Register 1 = 3 (", timeout=5)
    out, err = sniffer.finish()
    assert sniffer.proc.returncode == 0, err
    assert f"serial port {pty_pair.b} lost" in out
    assert "lost 1 times" in err
    # the log has the notices and the closing bus-health figures in /mbmon/events
    from mcap.reader import make_reader

    with open(log, "rb") as f:
        events = [
            json.loads(message.data)
            for _schema, channel, message in make_reader(f).iter_messages()
            if channel.topic == "/mbmon/events"
        ]
    text = json.dumps(events)
    assert "lost" in text and "is back" in text
    health = [e["info"] for e in events if e.get("event") == "stats" and "bus" in e["info"]]
    assert health and health[-1]["frames"] == 4 and "t35_violations" in health[-1]


def test_two_one_direction_taps_merge_into_one_bus(tmp_path: Path):
    """Reads are stamped when they return: the two writes are 30 ms apart so that a
    loaded test machine's scheduling delays (the test's, not the method's) cannot
    swap them; docs/sniffing.md says what this order can and cannot survive."""
    master = PtyPair(tmp_path / "mW", tmp_path / "mS")
    slave = PtyPair(tmp_path / "sW", tmp_path / "sS")
    master.start()
    slave.start()
    try:
        sniffer = SerialSniffer("--serial", str(master.b), "--serial", str(slave.b), "--json")
        fm = os.open(master.a, os.O_WRONLY | os.O_NOCTTY)
        fs = os.open(slave.a, os.O_WRONLY | os.O_NOCTTY)
        expected = []
        try:
            for unit, req, resp in _EXCHANGES:
                os.write(fm, _adu(unit, req))
                expected.append(req)
                time.sleep(0.03)
                if resp is not None:
                    os.write(fs, _adu(unit, resp))
                    expected.append(resp)
                    time.sleep(0.03)
        finally:
            os.close(fm)
            os.close(fs)
        sniffer.stdout_until(b'"11 04 01 FF 41 42"', timeout=5)
        out, err = sniffer.finish()
    finally:
        master.stop()
        slave.stop()
    assert sniffer.proc.returncode == 0, err
    frames = [r["pdu"] for r in _records(out) if r["kind"] in ("request", "response", "exception")]
    want = [" ".join(f"{b:02X}" for b in bytes.fromhex(p.replace(" ", ""))) for p in expected]
    assert frames == want
    kinds = [r["kind"] for r in _records(out) if r["kind"] != "event"]
    assert "noise" not in kinds


def _sniff_fails(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mbmon", "sniff", *args],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=30,
    )


def test_serial_missing_port_is_a_clear_error(tmp_path: Path):
    proc = _sniff_fails("--serial", str(tmp_path / "ttyNONE"))
    assert proc.returncode == 1
    assert f"cannot open serial port {tmp_path / 'ttyNONE'}" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_file_that_is_no_serial_port_says_so():
    proc = _sniff_fails("--serial", "/dev/null")
    assert proc.returncode == 1
    assert proc.stderr == (
        "mbmon: cannot open serial port /dev/null: not a serial port (it takes no line settings)\n"
    )


def test_an_unknown_output_format_is_refused_before_the_port_opens(pty_pair: PtyPair):
    proc = _sniff_fails("--serial", str(pty_pair.b), "-w", "bus.foo")
    assert proc.returncode == 2
    assert "bus.foo: unknown output format '.foo'" in proc.stderr
    assert "sniffing" not in proc.stderr and "Traceback" not in proc.stderr


def test_bus_health_warnings_reach_the_screen_the_log_and_the_summary(
    pty_pair: PtyPair, tmp_path: Path
):
    """What a listener at the wrong baud rate behind an FTDI adapter (16 ms latency
    timer) gets: bytes that frame as nothing, read in bursts 16 ms apart. Both
    warnings are printed as they are found, are NOTICE events in the log's
    ``/mbmon/events`` next to the bus-health STATS (gap histogram included) and
    are repeated in the summary; frames that follow are still found by CRC."""
    log = tmp_path / "health.mcap"
    sniffer = SerialSniffer("--serial", str(pty_pair.b), "--plain", "-w", str(log))
    rng = random.Random(7)
    junk = bytes(rng.randrange(256) for _ in range(29 * 24))
    pieces: list[Piece] = [(junk[i : i + 29], 0.016, True) for i in range(0, len(junk), 29)]
    exchange = _adu(1, "03 0000 0001") + _adu(1, "03 02 002A")
    pieces += [(exchange, 0.016, True)] * 4
    _write(pty_pair.a, pieces)
    sniffer.stdout_until(b"likely a wrong baud rate", timeout=5)
    sniffer.stdout_until(b"reads arrive in bursts", timeout=5)
    sniffer.stdout_until(b"03 02 00 2A", timeout=5)
    out, err = sniffer.finish()
    assert sniffer.proc.returncode == 0, err
    assert "(listening at 115200 8N1" in out and "latency_timer" in out

    from mcap.reader import make_reader

    with open(log, "rb") as f:
        events = [
            json.loads(message.data)
            for _schema, channel, message in make_reader(f).iter_messages()
            if channel.topic == "/mbmon/events"
        ]
    notices = [str(e["info"].get("message")) for e in events if e.get("event") == "notice"]
    assert any("likely a wrong baud rate" in n for n in notices), notices
    assert any("reads arrive in bursts" in n for n in notices), notices
    health = [e["info"] for e in events if e.get("event") == "stats" and "bus" in e["info"]]
    assert health, events
    last = health[-1]
    assert last["timing_useful"] is False and last["read_interval_ms"] >= 10
    assert last["noise_bytes"] * 2 > last["bytes"] and last["frames"] >= 2
    assert {"gap_lt_t35", "gap_lt_5ms", "gap_ge_1000ms", "gap_same_read"} <= set(last)

    warnings = [line for line in err.splitlines() if "warning:" in line]
    assert any("likely a wrong baud rate" in w for w in warnings), err
    assert any("reads arrive in bursts" in w for w in warnings), err
    assert "inter-frame gaps" in err and "timing NOT meaningful" in err


def _sniff_on_a_terminal(port: Path, writer: Path, extra: tuple[str, ...] = ()) -> str:
    """``mbmon sniff --serial PORT`` with stdout on a pseudo-terminal while one exchange
    crosses the bus: what the terminal showed (escapes and all)."""
    import pty
    import select

    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbmon", "sniff", "--serial", str(port), *extra],
        stdout=slave,
        stderr=subprocess.PIPE,
        env={**_env(), "COLUMNS": "400", "LINES": "40", "TERM": "xterm"},
        cwd=REPO,
    )
    _STARTED.append(proc)
    os.close(slave)
    shown = b""
    try:
        assert proc.stderr is not None
        assert b"sniffing" in proc.stderr.readline()
        _write(writer, [(_adu(1, "03 0000 0001") + _adu(1, "03 02 002A"), 0.0, False)])
        end = time.monotonic() + 5
        while b"03 02 00 2A" not in shown and time.monotonic() < end:
            if select.select([master], [], [], 0.1)[0]:
                shown += os.read(master, 65536)
        time.sleep(0.6)  # a few more ticks: the header has the bus figures by then
    finally:
        proc.send_signal(signal.SIGINT)
        end = time.monotonic() + 20
        while time.monotonic() < end:  # read on while it exits: a full terminal blocks it
            if not select.select([master], [], [], 0.2)[0]:
                if proc.poll() is not None:
                    break
                continue
            try:
                part = os.read(master, 65536)
            except OSError:
                break
            if not part:
                break
            shown += part
        proc.wait(5)
        os.close(master)
    return shown.decode("utf-8", "replace")


def test_a_terminal_gets_the_live_screen_with_bus_figures_and_a_pipe_plain_lines(
    pty_pair: PtyPair,
):
    # stdin and stdout a terminal: the monitor screen, its header with the bus figures
    sys.path.insert(0, str(REPO / "tests" / "monitor"))
    from term import Terminal

    term = Terminal(["sniff", "--serial", str(pty_pair.b)], 200, 40)
    try:
        term.wait_for(lambda s: " LIVE " in s)
        # a bus as it should be: each frame whole, the answer after a silence longer
        # than t3.5 (back to back, a loaded machine's reads may time the frames apart
        # and count the missing silence as the violation it is)
        _write(
            pty_pair.a, [(_adu(1, "03 0000 0001"), 0.05, True), (_adu(1, "03 02 002A"), 0.0, True)]
        )
        screen = term.wait_for(lambda s: "03 02 00 2A  | Read Holding Registers 0 = 42" in s)
        # the header's bus figures, whole (a repaint caught half way shows only some)
        screen = term.wait_for(
            lambda s: "CRC failures 0" in s and "t3.5 violations 0" in s and "noise bytes 0" in s
        )
        term.press("q")
        out = term.finish()
    finally:
        term.close()
    assert "╭" in screen and "monitor" in screen, screen
    assert "t3.5 violations 0" in screen and "noise bytes 0" in screen
    assert "mbmon: sniffed" in out or "sniffed" in out, out[-2000:]

    lines = _sniff_on_a_terminal(pty_pair.b, pty_pair.a, ("--plain",))
    assert "╭" not in lines and "CRC failures" not in lines
    assert re.search(r"^\S.*03 02 00 2A  \| Read Holding Registers 0 = 42", lines, re.M)

    # stdout a pipe, no --plain: plain lines too
    sniffer = SerialSniffer("--serial", str(pty_pair.b))
    _write(pty_pair.a, [(_adu(1, "03 0000 0001") + _adu(1, "03 02 002A"), 0.0, False)])
    sniffer.stdout_until(b"03 02 00 2A  | Read Holding Registers 0 = 42")
    out, err = sniffer.finish()
    assert sniffer.proc.returncode == 0, err
    assert "╭" not in out and "\x1b[" not in out
