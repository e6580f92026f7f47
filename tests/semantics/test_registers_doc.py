"""docs/registers.md is generated from the profiles: fail when the committed file is stale."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

from mbmon.semantics.profile import builtin_profile_text, load_profile, loads_profile

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "registers.md"


@pytest.fixture(scope="module")
def gen() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "gen_registers_doc", ROOT / "tools" / "gen_registers_doc.py"
    )
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_registers_doc_is_current(gen: ModuleType) -> None:
    fresh = gen.render(gen.builtin_profiles())
    assert DOC.read_text("utf-8") == fresh, (
        "docs/registers.md is stale: run python tools/gen_registers_doc.py"
    )


def test_doc_follows_profile_data(gen: ModuleType) -> None:
    base = gen.render([load_profile("hrss")])
    changed = loads_profile(builtin_profile_text("hrss").replace('1 = "Start"', '1 = "Go"'))
    other = gen.render([changed])
    assert base != other
    assert "SI1 Start" in base and "SI1 Go" in other


def test_doc_content(gen: ModuleType) -> None:
    text = DOC.read_text("utf-8")
    for needle in (
        "| 300..555 (299+n) | `DO[{n}]` |",
        "| 300..339 (298+2n) | `Timer[{n}]` |",
        "| 400..439 (398+2n) | `Counter[{n}]` |",
        "| 1000..1949 (1000+19(n−1)) | `PR[{n}]` |",
        "| 524 | `IR524` |",
        "| 771..774 | `IR771` | version ×4 |",
        "## Choices",
        "### SO1 sits at discrete input 0 (`hrss`)",
        "Table 45",
        "Table 47",
        "### XEG direction codes (`xeg`)",
    ):
        assert needle in text, needle


def test_check_mode(gen: ModuleType, tmp_path: Path) -> None:
    out = tmp_path / "registers.md"
    assert gen.main(["--check", "--output", str(out)]) == 1  # missing
    assert gen.main(["--output", str(out)]) == 0
    assert gen.main(["--check", "--output", str(out)]) == 0
    out.write_text(out.read_text("utf-8") + "edited by hand\n", "utf-8")
    assert gen.main(["--check", "--output", str(out)]) == 1
