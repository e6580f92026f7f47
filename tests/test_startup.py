"""A run imports what it uses, and nothing else: the fixed cost of every ``mbmon`` run.

Each test runs the real command line (``python -m mbmon ...`` from the repository
root, so this tree's ``mbmon`` is the one imported) in a child that prints, as it
exits, every module it imported. A change that drags a module back into a run
that does not use it (the annotator without ``--profile``, the reference pipeline
on a run the compiled core reads, another command's modules, the log's reader)
fails here. ``bench/startup.py`` measures what these runs cost.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from mbmon.commands import COMMANDS  # a run of one command never imports another command's module

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "captures" / "demo.pcap"

#: runs ``mbmon`` as ``python -m mbmon`` does, then prints the modules it imported
_WRAPPER = (
    "import runpy, sys\n"
    "sys.argv = ['mbmon', *sys.argv[1:]]\n"
    "try:\n"
    "    runpy.run_module('mbmon', run_name='__main__', alter_sys=True)\n"
    "finally:\n"
    "    sys.stderr.write('\\nMODULES ' + ' '.join(sorted(sys.modules)) + '\\n')\n"
)

#: the profiles' world: ``--profile`` only
ANNOTATOR = ["mbmon.semantics", "mbmon.semantics.annotate", "mbmon.semantics.profile", "tomllib"]
#: the reference pipeline, which a run the compiled core reads never needs
PIPELINE = ["mbmon.hub", "mbmon.pipeline", "mbmon.protocol.rtu", "mbmon.semantics.session"]
#: reading a log (``replay``, ``info``, ``export``), never writing one
LOG_READER = ["mbmon.io.mcap.summary", "mbmon.io.mcap.reader", "mcap.reader"]
#: writing a log: ``-w x.mcap`` only
LOG_WRITER = [
    "mbmon.sinks.mcap",
    "mbmon.io.mcap.layout",
    "mbmon.io.mcap.writer",
    "mcap",
    "zstandard",
]
#: never in a plain run (the screen's toolkit, live capture, serial lines, the simulator)
HEAVY = ["textual", "rich", "scapy", "serial", "pymodbus", "mbmon.monitor"]


def imported(*argv: str, pure: bool = False) -> tuple[set[str], subprocess.CompletedProcess[str]]:
    """The modules ``mbmon ARGV`` imported, and the run (its status and output)."""
    env = dict(os.environ)
    if pure:
        env["MBMON_NO_EXTENSIONS"] = "1"
    done = subprocess.run(
        [sys.executable, "-c", _WRAPPER, *argv],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    line = next(ln for ln in reversed(done.stderr.splitlines()) if ln.startswith("MODULES "))
    return set(line.split()[1:]), done


def other_commands(*keep: str) -> list[str]:
    return [f"mbmon.commands.{name}" for name in COMMANDS if name not in keep]


def assert_absent(modules: set[str], names: list[str], why: str) -> None:
    """None of ``names`` (nor a module under one of them) was imported."""
    found = sorted({m for m in modules for n in names if m == n or m.startswith(n + ".")})
    assert not found, f"{why}: imported {found}"


def _core_available() -> bool:
    out = subprocess.run(
        [sys.executable, "-c", "from mbmon import core; print(core.available())"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    )
    return out.stdout.strip() == "True"


needs_core = pytest.mark.skipif(
    not _core_available(),
    reason="the compiled core is off (MBMON_NO_EXTENSIONS) or not built in this tree "
    "(python3 setup.py build_ext --inplace)",
)
needs_demo = pytest.mark.skipif(not DEMO.exists(), reason="captures/demo.pcap absent")


@needs_core
@needs_demo
@pytest.mark.parametrize(
    "options",
    [["-q"], [], ["--json"], ["-q", "-w", "LOG"], ["-w", "LOG", "--json"]],
    ids=["quiet", "text", "json", "quiet-log", "json-log"],
)
def test_a_core_read_imports_neither_the_annotator_nor_the_pipeline(
    options: list[str], tmp_path: Path
) -> None:
    """``read F`` on the compiled core (plain, ``--json``, ``-q``, ``-w x.mcap``) imports
    the core and what it writes with: no annotator without ``--profile``, no hub or
    reference pipeline, no other command, no log reader, a log writer only with ``-w``."""
    log = tmp_path / "x.mcap"
    argv = [str(log) if o == "LOG" else o for o in options]
    modules, done = imported("read", str(DEMO), "--debug-core", *argv)
    assert done.returncode == 0, done.stderr
    assert "core: the compiled core read the input" in done.stderr
    assert "mbmon.core._reader" in modules
    assert_absent(modules, ANNOTATOR, "no --profile")
    assert_absent(modules, PIPELINE, "the core read the input")
    assert_absent(modules, other_commands("read"), "a read")
    assert_absent(modules, LOG_READER, "no log is read")
    assert_absent(modules, HEAVY, "a plain read")
    if "-w" in options:
        assert log.stat().st_size > 0
        assert {"mbmon.sinks.mcap", "mbmon.io.mcap.writer"} <= modules
        assert_absent(modules, ["mcap"], "the log's writer packs its own records")
    else:
        assert_absent(modules, LOG_WRITER, "no -w")
    if "-q" in options:
        assert_absent(modules, ["mbmon.sinks.console", "mbmon.sinks.summary"], "-q")


@needs_demo
def test_a_pure_read_imports_no_annotator_either() -> None:
    """The reference pipeline (``MBMON_NO_EXTENSIONS=1``) needs the hub, not the
    profiles' modules, and never loads the compiled core."""
    modules, done = imported("read", str(DEMO), "-q", "--debug-core", pure=True)
    assert done.returncode == 0, done.stderr
    assert "mbmon.pipeline" in modules  # it did read, through the pipeline
    assert_absent(modules, ["mbmon.core._reader", *ANNOTATOR], "pure, no --profile")
    assert_absent(modules, other_commands("read"), "a read")


@needs_demo
def test_profile_brings_the_annotator() -> None:
    """The other side of the checks above: ``--profile`` does import the annotator (the
    wrapper sees a module a run imports late, inside a function)."""
    modules, done = imported("read", str(DEMO), "-q", "--profile", "hrss")
    assert done.returncode == 0, done.stderr
    assert {"mbmon.semantics.annotate", "tomllib"} <= modules


def test_help_builds_the_commands_without_the_core() -> None:
    """``mbmon --help`` lists every command (each module imported to register it) but
    loads no compiled core, no profile, no log reader or writer."""
    modules, done = imported("--help")
    assert done.returncode == 0
    assert all(f"  {name}" in done.stdout for name in COMMANDS)
    assert {f"mbmon.commands.{name}" for name in COMMANDS} <= modules
    assert_absent(modules, ["mbmon.core", "mbmon.format", *ANNOTATOR, *PIPELINE], "--help")
    assert_absent(modules, [*LOG_READER, *LOG_WRITER, *HEAVY], "--help")


def test_a_commands_help_builds_that_command_only() -> None:
    """``mbmon read --help``: the read parser alone, no source or core module."""
    modules, done = imported("read", "--help")
    assert done.returncode == 0 and done.stdout.startswith("usage: mbmon read")
    assert_absent(modules, other_commands("read"), "read --help")
    assert_absent(modules, ["mbmon.core", "mbmon.sources.files", "mbmon.format"], "read --help")


def test_version_imports_the_core_and_no_command() -> None:
    """``mbmon --version`` says which core is active (it imports it to know) and builds
    no command's parser."""
    modules, done = imported("--version")
    assert done.returncode == 0 and done.stdout.startswith("mbmon ")
    assert "mbmon.core" in modules
    assert_absent(modules, other_commands(), "--version")
    assert_absent(modules, [*ANNOTATOR, *PIPELINE, *LOG_READER, *LOG_WRITER], "--version")


def test_info_reads_a_log_without_the_core_or_the_pipeline(tmp_path: Path) -> None:
    """``mbmon info x.mcap`` reads the log: no other command, no core, no pipeline."""
    if not DEMO.exists():
        pytest.skip("captures/demo.pcap absent")
    log = tmp_path / "x.mcap"
    subprocess.run(
        [sys.executable, "-m", "mbmon", "read", str(DEMO), "-q", "-w", str(log)],
        cwd=REPO,
        check=True,
        timeout=120,
    )
    modules, done = imported("info", str(log))
    assert done.returncode == 0, done.stderr
    assert "mbmon.io.mcap.summary" in modules
    assert_absent(modules, other_commands("info"), "info")
    assert_absent(modules, ["mbmon.core", *ANNOTATOR, *PIPELINE, *HEAVY], "info")
