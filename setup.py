"""Build of mbmon's compiled core (Cython extension modules); everything else is in
pyproject.toml.

The extensions are optional: without Cython or a C compiler, or with
``MBMON_NO_EXTENSIONS=1`` at build time, the package installs pure Python and
runs the reference pipeline (``mbmon --version`` says which core is active).
``MBMON_CORE_ASAN=1`` builds the core with AddressSanitizer (CI's fuzz step).
"""

from __future__ import annotations

import os
import sys

from setuptools import setup
from setuptools.command.build_ext import build_ext


def _wanted() -> bool:
    return os.environ.get("MBMON_NO_EXTENSIONS", "") in ("", "0")


class OptionalBuildExt(build_ext):
    """A failed compile leaves the pure-Python package, with a warning, not a failed install."""

    def run(self) -> None:
        try:
            super().run()
        except Exception as exc:  # no compiler, no Python headers
            self._skipped(exc)

    def build_extension(self, ext):  # type: ignore[no-untyped-def]
        try:
            super().build_extension(ext)
        except Exception as exc:
            self._skipped(exc)

    @staticmethod
    def _skipped(exc: BaseException) -> None:
        print(
            f"warning: mbmon's compiled core was not built ({exc}); "
            "the pure-Python pipeline will run",
            file=sys.stderr,
        )


def _extensions() -> list:
    if not _wanted():
        return []
    try:
        from Cython.Build import cythonize
    except ImportError:
        print(
            "warning: Cython is missing; mbmon installs without its compiled core", file=sys.stderr
        )
        return []
    from setuptools import Extension

    args = ["-O2", "-ffp-contract=off"]  # the same float arithmetic as the reference
    link: list[str] = []
    if os.environ.get("MBMON_CORE_ASAN", "") not in ("", "0"):
        args = ["-O1", "-g", "-fno-omit-frame-pointer", "-fsanitize=address", "-ffp-contract=off"]
        link = ["-fsanitize=address"]
    ext = Extension(
        "mbmon.core._reader",
        ["mbmon/core/_reader.pyx"],
        extra_compile_args=args,
        extra_link_args=link,
    )
    # RTU framing (timing-free), a module of its own
    rtu = Extension(
        "mbmon.core._rtu",
        ["mbmon/core/_rtu.pyx"],
        extra_compile_args=args,
        extra_link_args=link,
    )
    return cythonize(
        [ext, rtu],
        language_level=3,
        compiler_directives={"boundscheck": True, "wraparound": False, "cdivision": True},
        quiet=True,
    )


setup(ext_modules=_extensions(), cmdclass={"build_ext": OptionalBuildExt})
