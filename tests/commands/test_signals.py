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
from long_capture import signal_while_logging, write_long_capture

from mbmon import core as mbmon_core
from mbmon.io.mcap.reader import McapLog

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "TZ": "UTC"}


@pytest.fixture(scope="module")
def long_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Modbus/TCP capture that takes mbmon many seconds to read (25 ADUs per segment)."""
    return write_long_capture(tmp_path_factory.mktemp("long") / "long.pcap", 12000)


@pytest.mark.parametrize("core", [False, True], ids=["pure", "core"])
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_read_to_mcap_ends_alike_on_sigterm_and_sigint(
    tmp_path: Path, long_capture: Path, sig: signal.Signals, core: bool
) -> None:
    if core and not mbmon_core.available():
        pytest.skip("the compiled core is not built (or MBMON_NO_EXTENSIONS is set)")
    rng = random.Random(17)
    for run in range(8):
        log = tmp_path / f"x{run}.mcap"
        returncode, err = signal_while_logging(
            long_capture, log, sig, rng.uniform(0.05, 1.5), core=core
        )
        what = f"run {run} ({sig.name}): exit {returncode}, stderr:\n{err}"
        assert returncode == 128 + sig, what
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
    delays = [0.0, 0.03, 0.08, 0.15] + [max(0.0, python_up + k * step) for k in range(-2, 14)]
    outcomes: list[tuple[float, int]] = []
    before: list[float] = []
    for delay in delays:
        proc = subprocess.Popen(
            # forced pure: the Python pipeline takes long enough over this capture to
            # be still reading when the last signals land (the core is done sooner)
            [sys.executable, *start, "read", str(long_capture), "-q", "-t", "r"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**ENV, "MBMON_NO_EXTENSIONS": "1"},
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


# --------------------------------------------------------------------------- no lost signal

#: when SIGINT comes, after the interpreter is up: 0.02 .. 0.4 s in 12 steps
SWEEP = [round(0.02 + 0.38 * k / 11, 3) for k in range(12)]


def _before_mbmon(proc: subprocess.Popen[str], err: str) -> bool:
    """Whether the signal came while the interpreter itself started (``site``, ``.pth``
    files, or Python's handler not installed yet), before a line of mbmon ran."""
    return (
        "init_import_site" in err
        or proc.returncode == -signal.SIGINT
        or ("Traceback" in err and "/mbmon/" not in err)
    )


def _interrupt_read(kind: str, capture: Path, delay: float) -> tuple[int, str] | None:
    """Start ``read -`` fed by a pipe that stays open (the capture's first 32 KiB in
    it), or ``read FILE``; SIGINT after ``delay`` s; its exit status and stderr, or
    ``None`` when the signal came before mbmon's code ran."""
    if kind == "pipe":
        read_end, write_end = os.pipe()
        argv = [sys.executable, "-m", "mbmon", "read", "-"]
    else:
        read_end, write_end = -1, -1
        argv = [sys.executable, "-m", "mbmon", "read", str(capture), "-t", "r"]  # no core
    try:
        proc = subprocess.Popen(
            argv,
            stdin=read_end if kind == "pipe" else subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        if kind == "pipe":
            os.close(read_end)
            with open(capture, "rb") as f:
                os.write(write_end, f.read(32 * 1024))  # fits the pipe: never blocks
        time.sleep(delay)
        assert proc.poll() is None, f"read ended before the signal: {proc.communicate()}"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if write_end >= 0:
            os.close(write_end)
    return None if _before_mbmon(proc, err) else (proc.returncode, err)


@pytest.mark.parametrize("kind", ["pipe", "file"])
def test_ctrl_c_at_any_instant_of_read_exits_130_without_a_traceback(
    long_capture: Path, kind: str
) -> None:
    """A SIGINT 0.02 .. 0.4 s after the interpreter is up (while mbmon imports, builds
    its parser, opens the input, reads it) ends ``read -`` (a pipe that stays open)
    and ``read FILE`` with 130 and no traceback, every time. A signal that lands in
    the interpreter's own start is tried again a little later (not mbmon's code)."""
    python_up = _wall([sys.executable, "-c", "pass"])
    for delay in SWEEP:
        outcome = None
        for attempt in range(6):
            outcome = _interrupt_read(kind, long_capture, python_up * (1 + attempt / 2) + delay)
            if outcome is not None:
                break
        assert outcome is not None, f"{kind} {delay}: every signal came before mbmon started"
        status, err = outcome
        what = f"{kind}, SIGINT {delay} s after start: exit {status}, stderr:\n{err}"
        assert status == 130, what
        assert "Traceback" not in err and "Exception ignored" not in err, what


_LATE_IMPORT = """\
import os, sys
from pathlib import Path
import mbmon.commands.read as read
Path(sys.argv[1], "late_module.py").write_text(
    "import os, signal\\nos.kill(os.getpid(), signal.SIGINT)\\nfor _ in range(10000): pass\\n"
)
sys.path.insert(0, sys.argv[1])
def run(args):
    import late_module  # a lazy import as the run ends; the signal comes inside it
    return 0
read.run = run
from mbmon.cli import main
sys.exit(main(["read", "x.pcap"]))
"""


def test_a_signal_deferred_past_the_last_import_of_a_run_still_ends_it_130(
    tmp_path: Path,
) -> None:
    """A signal that comes inside an import is raised once the import is over; when the
    command returns first, the signal was dropped with its retry timer and the run
    exited 0. It is recorded when it comes: 130."""
    proc = subprocess.run(
        [sys.executable, "-c", _LATE_IMPORT, str(tmp_path)],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=120,
    )
    assert proc.returncode == 130, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr


_SWALLOWED = """\
import os, signal, sys, time, weakref
from mbmon.commands.common import install_signal_handlers
install_signal_handlers()
class Finalized:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGINT)  # the handler runs here, in the finalizer
        for _ in range(1000): pass
class Referent:
    pass
def callback(ref):
    os.kill(os.getpid(), signal.SIGINT)  # as in the import system's module-lock cleanup
    for _ in range(1000): pass
try:
    if sys.argv[1] == "finalizer":
        Finalized()
    else:
        referent = Referent(); ref = weakref.ref(referent, callback); del referent
    time.sleep(5)
    print("lost")
except KeyboardInterrupt as exc:
    print("interrupted", exc.signum)
"""


@pytest.mark.parametrize("where", ["finalizer", "weakref callback"])
def test_a_signal_whose_exception_python_swallows_is_raised_again(where: str) -> None:
    """The handler raises where the main thread is; in a finalizer or a weakref callback
    Python prints "Exception ignored" and drops the exception: the run went on as if
    no signal came. It is raised again a moment later, quietly."""
    proc = subprocess.run(
        [sys.executable, "-c", _SWALLOWED, where.split()[0]],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=120,
    )
    assert proc.stdout == "interrupted 2\n", proc.stdout + proc.stderr
    assert "Exception ignored" not in proc.stderr, proc.stderr


_SIGINT_WHILE_CLI_IMPORTS = """
import os, signal as _already, sys

class _Interrupting:
    # a Ctrl-C arriving exactly while mbmon.cli reads the 'signal' module from disk
    def find_spec(self, name, path=None, target=None):
        if name == "signal":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), _already.SIGINT)
        return None

del sys.modules["signal"]
sys.meta_path.insert(0, _Interrupting())
from mbmon.cli import main
sys.exit(main())
"""


def test_ctrl_c_while_the_console_script_imports_the_cli_exits_130_quietly() -> None:
    """The console script imports mbmon.cli before main() can install a handler: a
    Ctrl-C during that import (here: exactly while 'signal' is imported) still ends
    the run quietly with 130, not with a traceback."""
    proc = subprocess.run(
        [sys.executable, "-c", _SIGINT_WHILE_CLI_IMPORTS, "read", "/nonexistent.pcap"],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=60,
    )
    assert proc.returncode == 130, (proc.returncode, proc.stderr)
    assert "Traceback" not in proc.stderr and "KeyboardInterrupt" not in proc.stderr, proc.stderr
