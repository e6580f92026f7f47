"""The RS485 corpus through the commands: ``read --rtu-raw`` on a dump and
``sniff --serial`` on a real socat pty pair.

* libmodbus's RTU unit-test session with noise bursts between frames: every
  frame exactly once, in order, libmodbus's quantity-0 writes as malformed
  requests paired with their exception answers.
* On a pty, a bad-CRC read and then six good frames 0.3 s apart: each frame is
  printed before the next is written, stamped with its own time; the bad read is
  one noise record.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rtu_corpus import BAD_CRC, BAD_REQUESTS, GOOD, bus_directions, session
from socat_ptys import pty_pair

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}

#: noise put between the session's frames: line glitches and a bad-CRC copy
NOISE = [bytes.fromhex("00"), bytes.fromhex("FF FF"), BAD_CRC, bytes.fromhex("00 FE 80")]


def _records(stdout: str) -> list[dict[str, object]]:
    return [json.loads(line) for line in stdout.splitlines() if line.strip()]


def test_read_rtu_raw_session_with_noise_each_frame_once(tmp_path: Path) -> None:
    frames = session()
    parts: list[bytes] = []
    noise = 0
    for i, (who, raw) in enumerate(frames):
        # noise before some of the master's frames, after an answer: a frame whose
        # fields disagree ends where the bus marks it (silence, next frame), and an
        # untimed dump has no silence to mark it when noise is glued right after it
        if i % 9 == 4 and who == ">" and frames[i - 1][0] == "<":
            junk = NOISE[i % len(NOISE)]
            parts.append(junk)
            noise += len(junk)
        parts.append(raw)
    dump = tmp_path / "bus.bin"
    dump.write_bytes(b"".join(parts))
    proc = subprocess.run(
        [sys.executable, "-m", "mbmon", "read", "--rtu-raw", str(dump), "--json"],
        capture_output=True,
        text=True,
        env=ENV,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    records = _records(proc.stdout)
    got = [
        (r["kind"] == "request", bytes.fromhex(str(r["pdu"])))
        for r in records
        if r["kind"] in ("request", "response", "exception")
    ]
    want = [(d.value == "c2s", raw[1:-2]) for d, raw in bus_directions(frames)]
    assert got == want  # each frame once, in order, as request or answer
    assert sum(len(str(r["pdu"]).split()) for r in records if r["kind"] == "noise") == noise
    # the quantity-0 write and its exception answer are a pair, not noise
    req = BAD_REQUESTS[0][0]
    i = next(n for n, r in enumerate(records) if r["pdu"] == req[1:-2].hex(" ").upper())
    assert records[i]["kind"] == "request" and records[i + 1]["kind"] == "exception"
    assert "(no matching request)" not in str(records[i + 1]["line"])


@pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")
def test_sniff_serial_frames_after_noise_each_at_its_own_time() -> None:
    with pty_pair() as (writer_end, sniff_end):
        proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "sniff", "--serial", sniff_end, "--json"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=ENV,
            cwd=REPO,
        )
        try:
            assert proc.stderr is not None and proc.stdout is not None
            err = b""
            deadline = time.monotonic() + 20
            while b"sniffing" not in err:
                assert time.monotonic() < deadline and proc.poll() is None, err
                if select.select([proc.stderr], [], [], 0.1)[0]:
                    err += os.read(proc.stderr.fileno(), 4096)
            fd = os.open(writer_end, os.O_RDWR | os.O_NOCTTY)
            out = b""
            shown: list[tuple[float, float]] = []  # (written, printed) per frame
            writes = [BAD_CRC] + [GOOD] * 6 + [BAD_REQUESTS[0][0], BAD_REQUESTS[0][1]]
            try:
                for n, data in enumerate(writes):
                    written = time.time()
                    os.write(fd, data)
                    if n == 0:
                        time.sleep(0.3)
                        continue
                    # the frame's line comes before the next write (0.3 s on)
                    end = time.monotonic() + 0.3
                    lines = out.count(b"\n")
                    while time.monotonic() < end:
                        if select.select([proc.stdout], [], [], 0.02)[0]:
                            out += os.read(proc.stdout.fileno(), 65536)
                        if out.count(b"\n") > lines and n not in (1, 7):
                            break  # (1 and 7 also print what they settle)
                    shown.append((written, time.time()))
            finally:
                os.close(fd)
            time.sleep(0.2)
            proc.send_signal(signal.SIGINT)
            rest, tail = proc.communicate(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    records = _records((out + rest).decode())
    frames = [r for r in records if r["kind"] in ("request", "response", "exception")]
    good = [r for r in frames if r["pdu"] == "03 01 60 00 01"]
    assert len(good) == 6
    # each stamped with its own time (the reader's), not the last one's
    for (written, _), r in zip(shown, good, strict=False):
        assert abs(float(str(r["time"])) - written) < 0.25
    assert len({r["time"] for r in good}) == 6
    noise = [r for r in records if r["kind"] == "noise"]
    assert [r["pdu"] for r in noise] == [BAD_CRC.hex(" ").upper()]  # one run, one record
    bad = [r for r in frames if r["pdu"] == BAD_REQUESTS[0][0][1:-2].hex(" ").upper()]
    assert len(bad) == 1 and bad[0]["kind"] == "request"
    assert frames[-1]["kind"] == "exception" and "(no matching request)" not in str(
        frames[-1]["line"]
    )
    # the lines came out as the frames did: none waited for the next frame
    assert out.count(b'"03 01 60 00 01"') >= 5, (out + rest).decode() + tail.decode()
