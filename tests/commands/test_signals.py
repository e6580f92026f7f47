"""SIGINT and SIGTERM end a command the same way, at any instant (real subprocesses).

- ``read CAPTURE -w LOG.mcap`` stopped by SIGTERM ends as Ctrl-C does: the log is
  finished (summary and index), the summary is printed, and a message names the
  log; the exit status is 128 + the signal (143; 130 for Ctrl-C). Repeated at
  random moments: the field saw the summary and message missing in 7 of 8 runs.
- A Ctrl-C that comes while mbmon is still importing its modules (the first
  ~0.15 s of any command) exits 130 quietly: no traceback. (One that comes while
  the interpreter itself is still starting, importing ``site``, or on the entry
  script's import statement, comes before any code of mbmon runs: not judged.)
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from long_capture import write_long_capture

from mbmon.io.mcap.reader import McapLog

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "TZ": "UTC"}


@pytest.fixture(scope="module")
def long_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Modbus/TCP capture that takes mbmon many seconds to read (25 ADUs per segment)."""
    return write_long_capture(tmp_path_factory.mktemp("long") / "long.pcap", 12000)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_read_to_mcap_ends_alike_on_sigterm_and_sigint(
    tmp_path: Path, long_capture: Path, sig: signal.Signals
) -> None:
    rng = random.Random(17)
    for run in range(8):
        log = tmp_path / f"x{run}.mcap"
        proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", "read", str(long_capture), "-w", str(log)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        deadline = time.monotonic() + 60
        while not log.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)  # the log is open: records flow from now on
        time.sleep(rng.uniform(0.05, 1.5))
        assert proc.poll() is None, "the input must outlast the test"
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
        what = f"run {run} ({sig.name}): exit {proc.returncode}, stderr:\n{err}"
        assert proc.returncode == 128 + sig, what
        assert "Traceback" not in err, what
        assert " frames (" in err and "requests" in err, what  # the summary
        assert f"interrupted; {log} was finished and is complete up to here" in err, what
        with McapLog(log) as opened:
            assert opened.finished, what
            assert sum(1 for _ in opened.messages(["/modbus/monitor"])) > 0


_CONSOLE_SCRIPT = "import sys\nfrom mbmon.cli import main\nsys.exit(main())\n"


@pytest.mark.parametrize("entry", ["-m mbmon", "console script"])
def test_ctrl_c_while_starting_exits_130_quietly(long_capture: Path, entry: str) -> None:
    """SIGINT at several short delays after start: while Python and mbmon import their
    modules, while the parser is built, and once the command runs."""
    start = ["-m", "mbmon"] if entry == "-m mbmon" else ["-c", _CONSOLE_SCRIPT]
    # the window moves with the machine's load: from when the interpreter is up to
    # when mbmon has imported what `read` needs, measured now
    python_up = _wall([sys.executable, "-c", "pass"])
    mbmon_up = _wall([sys.executable, *start, "read", "/nonexistent.pcap"])
    step = max(mbmon_up - python_up, 0.05) / 10
    delays = [0.0, 0.03, 0.08, 0.15] + [python_up + k * step for k in range(-2, 14)]
    outcomes: list[tuple[float, int]] = []
    before: list[float] = []
    for delay in delays:
        proc = subprocess.Popen(
            # -t r keeps the compiled core off: the Python pipeline takes long enough
            # over this capture to be still reading when the last signals land
            [sys.executable, *start, "read", str(long_capture), "-q", "-t", "r"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        time.sleep(delay)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
        if "init_import_site" in err or ("Traceback" in err and "/mbmon/" not in err):
            # the interpreter's own start (site, .pth files) or the entry's first import
            # statement, before a line of mbmon ran (milliseconds on an idle machine)
            before.append(delay)
            continue
        outcomes.append((delay, proc.returncode))
        # before Python installs its own SIGINT handler, the default action ends the
        # process (-2, as a shell reports 130); from then on mbmon's exit status
        assert proc.returncode in (130, -signal.SIGINT), (delay, proc.returncode, err)
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, (delay, err)
        assert not out, (delay, out)
    assert len(outcomes) >= 5 and any(code == 130 for _, code in outcomes), (outcomes, before)


def _wall(argv: list[str]) -> float:
    """Wall time of a command (the median of three runs)."""
    times = []
    for _ in range(3):
        started = time.monotonic()
        subprocess.run(argv, capture_output=True, env=ENV, timeout=120)
        times.append(time.monotonic() - started)
    return sorted(times)[1]
