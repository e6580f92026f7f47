"""A real pseudo-terminal for the monitor's tests: a command runs with its stdout, stdin
and stderr on a pty of a given size, and what it draws is read back through pyte (a
VT100 emulator), as a user's terminal would show it."""

from __future__ import annotations

import fcntl
import os
import select
import struct
import subprocess
import sys
import termios
import time
from collections.abc import Callable
from pathlib import Path

import pyte

REPO = Path(__file__).resolve().parents[2]


class Terminal:
    """``mbmon ARGS`` on a pty of ``columns`` x ``lines``; :meth:`text` is the screen."""

    def __init__(self, args: list[str], columns: int = 160, lines: int = 50,
                 cwd: Path | None = None) -> None:  # fmt: skip
        self.screen = pyte.Screen(columns, lines)
        self.stream = pyte.ByteStream(self.screen)
        master, slave = os.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", lines, columns, 0, 0))
        env = {**os.environ, "TERM": "xterm-256color", "COLUMNS": str(columns),
               "LINES": str(lines), "PYTHONPATH": str(REPO)}  # fmt: skip
        env.pop("NO_COLOR", None)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "mbmon", *args],
            stdin=slave,
            stdout=slave,
            stderr=slave,
            cwd=cwd or REPO,
            env=env,
            start_new_session=True,
        )
        os.close(slave)
        self.master = master
        self.raw = b""

    def pump(self, seconds: float = 0.1) -> None:
        """Read what the program drew for up to ``seconds``."""
        end = time.monotonic() + seconds
        while True:
            left = end - time.monotonic()
            if left <= 0:
                return
            if select.select([self.master], [], [], left)[0]:
                try:
                    data = os.read(self.master, 65536)
                except OSError:
                    return
                if not data:
                    return
                self.raw += data
                self.stream.feed(data)

    def text(self) -> str:
        return "\n".join(self.screen.display)

    def wait_for(self, found: Callable[[str], bool], timeout: float = 30.0) -> str:
        """Pump until ``found(screen text)``; the text, or AssertionError with the screen."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.pump(0.2)
            text = self.text()
            if found(text):
                return text
            if self.proc.poll() is not None:
                self.pump(0.5)
                break
        raise AssertionError(f"not on the screen within {timeout} s:\n{self.text()}")

    def press(self, keys: str, settle: float = 0.3) -> None:
        os.write(self.master, keys.encode())
        self.pump(settle)

    def finish(self, timeout: float = 30.0) -> str:
        """Wait for the program to end; everything it wrote after the screen, as text."""
        end = time.monotonic() + timeout
        while self.proc.poll() is None and time.monotonic() < end:
            self.pump(0.2)
        self.pump(0.5)
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
            raise AssertionError(f"still running after {timeout} s:\n{self.text()}")
        os.close(self.master)
        return self.raw.decode("utf-8", "replace")

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
        try:
            os.close(self.master)
        except OSError:
            pass
