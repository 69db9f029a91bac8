"""`rangeret predict --overwrite` and the Ray job (`python -m workers.predict_job --overwrite`),
the real command lines, with an output folder whose `predictions` folder is a link to the
dataset's own labels: every output path is resolved before a byte is written, the run is refused
in one sentence and the dataset is left as it was."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.gateway import NET
from tests.support.paths import REPO
from tests.support.workers import build_tree, small_weights


def _snapshot(root: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}


@pytest.mark.slow
@pytest.mark.parametrize("command", [["rangeret.cli.main", "predict"], ["workers.predict_job"]])
def test_predictions_never_land_on_the_datasets_labels(command, tmp_path):
    data = build_tree(tmp_path / "data", labelled=1, unlabelled=0)
    weights = small_weights(tmp_path)
    out = tmp_path / "out"
    (out / "sequences" / "08").mkdir(parents=True)
    (out / "sequences" / "08" / "predictions").symlink_to(data / "sequences" / "08" / "labels")
    before = _snapshot(data)
    args = ["-q", "--dataset", str(data), "--sequences", "08", "--out", str(out), "--overwrite"]
    done = subprocess.run(
        [sys.executable, "-m", *command, *args, "--checkpoint", str(weights), *NET],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 1, done.stderr[-2000:]
    label = data / "sequences" / "08" / "labels" / "000000.label"
    assert f"leads to the input file {label}" in done.stderr and "Traceback" not in done.stderr
    assert _snapshot(data) == before
