"""A small 64-beam source tree written by `rangeret simulate`, and 32-beam target profiles
(+10 to -30 degrees, 32 x 256) made by editing the semantickitti profile's fields."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from rangeret.cli.main import main
from rangeret.dataset.profiles import DatasetProfile, load_profile

#: The source tree's sequences and scans (SemanticKITTI's layout and record, 64 beams).
SOURCE_SEQUENCES = ("00", "08")


def write_target(path: Path, *, ring: bool = False, **sensor: Any) -> Path:
    """A 32-beam target profile in `ROOT/scans/NNN`, max range 40 m; with `ring`, 8-bit
    intensities and each point's ring in its record."""
    data = load_profile("semantickitti").to_dict()
    data["name"] = "test-32"
    data["sensor"].update(height=32, width=256, fov_up=10.0, fov_down=-30.0, max_range=40.0)
    data["layout"] = {"sequence_folders": ["scans"], "id_digits": 3}
    if ring:
        data["points"] = {"fields": ["x", "y", "z", "intensity", "ring"]}
        data["sensor"].update(row="ring", reflectance_max=255.0)
    data["sensor"].update(sensor)
    path.write_text(DatasetProfile.from_dict(data).to_yaml())
    return path


@pytest.fixture(scope="package")
def source_tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two scans of sequence 00 and one of 08, labelled, 64 x 512 rays each."""
    root = tmp_path_factory.mktemp("adapt") / "source"
    argv = ["simulate", "-q", "--out", str(root), "--sequences", "0:2", "8:1"]
    assert main([*argv, "--azimuth-steps", "512", "--seed", "4"]) == 0
    return root


@pytest.fixture
def adapt(capsys: pytest.CaptureFixture[str]) -> Callable[..., tuple[int, str, str]]:
    """Run `rangeret adapt -q` with the given options; (exit code, stdout, stderr)."""

    def run(*argv: str) -> tuple[int, str, str]:
        code = main(["adapt", "-q", *argv])
        captured = capsys.readouterr()
        return code, captured.out, captured.err

    return run
