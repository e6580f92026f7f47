"""The live monitor's state panel is the annotator's decision: shown when a profile
in force names a device session, whatever the ``--profile`` text says."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

import mbmon.semantics
from mbmon.commands.common import make_annotator, wants_state_panel

PROFILES = Path(mbmon.semantics.__file__).parent / "profiles"


@pytest.mark.parametrize(
    ("specs", "panel"),
    [
        ([], False),
        (["hrss"], True),
        (["xeg"], False),
        (["127.0.0.1:502=hrss"], True),
        (["unit:2=xeg", "unit:1=hrss"], True),
        (["unit:3=xeg"], False),
    ],
)
def test_built_in_profiles(specs: list[str], panel: bool) -> None:
    assert wants_state_panel(make_annotator(specs)) is panel


def test_the_session_decides_not_the_name(tmp_path: Path) -> None:
    """A copy of the HRSS map under another name has the session: the panel. A
    session-less map in a folder called ``hrss`` has none: no panel (the old test
    of the spelling answered both the other way)."""
    cell = tmp_path / "cell.toml"
    shutil.copy(PROFILES / "hrss.toml", cell)
    assert wants_state_panel(make_annotator([str(cell)])) is True
    folder = tmp_path / "hrss"
    folder.mkdir()
    gripper = folder / "gripper.toml"
    shutil.copy(PROFILES / "xeg.toml", gripper)
    assert wants_state_panel(make_annotator([str(gripper)])) is False
    assert wants_state_panel(None) is False
