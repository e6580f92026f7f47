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
