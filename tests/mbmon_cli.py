"""The one way tests run the ``mbmon`` command line in a child process."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def mbmon(
    *args: str | Path, cwd: Path | None = None, timeout: float = 300
) -> subprocess.CompletedProcess[str]:
    """``python -m mbmon ARGS`` from the repository (or ``cwd``): exit status, stdout
    and stderr as text; never raises for a non-zero exit."""
    return subprocess.run(
        [sys.executable, "-m", "mbmon", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd or REPO,
        timeout=timeout,
    )
