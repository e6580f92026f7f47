"""`import mbmon` and the pure layers must not pull in scapy or pyserial (DESIGN rule 8)."""

import subprocess
import sys

import pytest

MODULES = [
    "mbmon",
    "mbmon.model",
    "mbmon.format",
    "mbmon.pipeline",
    "mbmon.cli",
    "mbmon.protocol.pdu",
    "mbmon.protocol.mbap",
    "mbmon.protocol.rtu",
    "mbmon.protocol.pairing",
    "mbmon.semantics.annotate",
    "mbmon.sources.pcapfile",
]


@pytest.mark.parametrize("module", MODULES)
def test_no_heavy_imports(module: str) -> None:
    code = (
        f"import sys, {module}; "
        "bad = [m for m in ('scapy', 'serial', 'pymodbus') if m in sys.modules]; "
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"{module} imports {out.stdout.strip()}"


IO_MODULES = [
    "mbmon.io.replay",
    "mbmon.io.mcap",
    "mbmon.io.mcap.reader",
    "mbmon.io.mcap.layout",
    "mbmon.io.mcap.writer",
    "mbmon.io.mcap.reader",
    "mbmon.sinks.mcap",
]


@pytest.mark.parametrize("module", IO_MODULES)
def test_io_does_not_import_the_cli(module: str) -> None:
    """Dependencies point down: the log modules never pull in the command line (issue 9)."""
    code = (
        f"import sys, {module}; "
        "bad = [m for m in ('mbmon.cli', 'mbmon.commands', 'mbmon.logcmds') if m in sys.modules]; "
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"{module} imports {out.stdout.strip()}"


def test_the_mcap_reader_does_not_import_the_writer() -> None:
    code = (
        "import sys, mbmon.io.mcap.reader; "
        "print(','.join(m for m in ('mbmon.io.mcap.writer', 'mbmon.io.mcap.layout', "
        "'mbmon.sinks.mcap') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
