"""`python -m workers.adapt_job` on a local Ray: the same tree as `rangeret adapt`, resumed, and a
scan that cannot be adapted named in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rangeret.cli.main import main as rangeret_main
from rangeret.io.scans import read_labels
from tests.rangeret.adapt.conftest import write_target
from workers.adapt_job import main as job_main

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three labelled scans of a 64-beam sensor in sequences 00 and 08."""
    root = tmp_path_factory.mktemp("adapt-job") / "source"
    argv = ["simulate", "-q", "--out", str(root), "--sequences", "0:2", "8:1"]
    assert rangeret_main([*argv, "--azimuth-steps", "512", "--seed", "7"]) == 0
    return root


def _options(source: Path, target: Path, out: Path, *more: str) -> list[str]:
    return [
        "--dataset",
        str(source),
        "--profile",
        "semantickitti",
        "--to-profile",
        str(target),
        "--out",
        str(out),
        "--sequences",
        "00",
        "08",
        "--sensor-offset",
        "0.2",
        "0",
        "0.3",
        *more,
    ]


def _scans(root: Path) -> dict[str, bytes]:
    """The scan and label files of a tree, by relative path (adapt.json records times)."""
    files = sorted(p for p in root.rglob("*") if p.suffix in (".bin", ".label"))
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in files}


def test_the_job_writes_the_tree_rangeret_adapt_writes(ray_local, source, tmp_path, capsys):
    target = write_target(tmp_path / "t.yaml", ring=True)
    assert rangeret_main(["adapt", "-q", *_options(source, target, tmp_path / "one")]) == 0
    assert job_main(["-q", *_options(source, target, tmp_path / "ray")]) == 0
    out = capsys.readouterr().out
    assert "scans adapted into" in out and ": 3" in out
    one, ray = _scans(tmp_path / "one"), _scans(tmp_path / "ray")
    assert len(one) == 6 and one == ray

    # A second run finds every scan done and rewrites none of them.
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "ray").rglob("*.bin")}
    assert job_main(["-q", *_options(source, target, tmp_path / "ray")]) == 0
    assert "(3 already there)" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "ray").rglob("*.bin")} == before


def test_a_scan_that_cannot_be_adapted_is_one_line(ray_local, source, tmp_path, capsys):
    labels = read_labels(source / "sequences" / "00" / "labels" / "000000.label")
    ids = np.unique(labels & 0xFFFF).tolist()
    path = tmp_path / "map.yaml"
    path.write_text("".join(f"{i}: 10\n" for i in ids[1:]))
    target = write_target(tmp_path / "t.yaml")
    argv = _options(source, target, tmp_path / "out", "--label-map", str(path))
    assert job_main(["-q", *argv]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    # Whichever scan fails first is named, with the first id of it the map lacks.
    assert len(err) == 1 and f"is not in the label map {path}" in err[0]
    assert err[0].startswith("adapt_job: error: 0") and ": raw id " in err[0]
    assert "Traceback" not in err[0] and "RayTaskError" not in err[0]
