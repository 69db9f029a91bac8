"""`write_nuscenes_results`: the results folder of any keyframes, each split folder their
predictions lie in with its submission.json, written by the same code as `rangeret submission`."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.dataset.profiles import load_profile
from rangeret.dataset.table_layout import prediction_split
from rangeret.io.scans import scan_num_points
from rangeret.submission.archives import SubmissionError
from rangeret.submission.nuscenes import write_nuscenes_results
from tests.support.nuscenes import entries, write_tree

PROFILE = load_profile("nuscenes")


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tree(tmp_path_factory.mktemp("nu") / "nu", {"scene-0061": 1, "scene-0916": 2})


def _predict(tree: Path, pred: Path) -> list:
    """Every keyframe of both scenes (in their own split folders) predicted as class 4."""
    scans = entries(tree, ["scene-0061", "scene-0916"])
    for entry in scans:
        count = scan_num_points(entry.scan_path, record=PROFILE.points)
        entry.label_file.write(entry.prediction_in(pred), np.full(count, 4))
    return scans


def test_each_split_folder_gets_its_predictions_and_submission_json(tmp_path, tree):
    scans = _predict(tree, tmp_path / "pred")
    assert [prediction_split(e) for e in scans] == ["mini_train", "mini_val", "mini_val"]
    out = tmp_path / "results.zip"
    write_nuscenes_results(
        tmp_path / "pred", scans, out, profile=PROFILE, submission="{}\n", description="d"
    )
    with zipfile.ZipFile(out) as zf:
        names = zf.namelist()
        assert names[:5] == ["lidarseg/", "lidarseg/mini_train/", "mini_train/",
                             "lidarseg/mini_val/", "mini_val/"]  # fmt: skip
        assert names[5:8] == [e.prediction for e in scans]
        assert names[8:] == ["mini_train/submission.json", "mini_val/submission.json",
                             "description.txt"]  # fmt: skip
        for entry in scans:
            assert zf.read(entry.prediction) == entry.prediction_in(tmp_path / "pred").read_bytes()


def test_a_missing_prediction_writes_nothing(tmp_path, tree):
    scans = _predict(tree, tmp_path / "pred")
    scans[1].prediction_in(tmp_path / "pred").unlink()
    out = tmp_path / "results.zip"
    with pytest.raises(SubmissionError, match=f"{scans[1].name}_lidarseg.bin is missing"):
        write_nuscenes_results(
            tmp_path / "pred", scans, out, profile=PROFILE, submission="{}\n", description="d"
        )
    assert not out.exists() and list(tmp_path.glob("*.zip*")) == []


def test_a_submission_json_nested_too_deeply_is_one_problem(tmp_path, tree):
    """The validator names a submission.json nested 30,000 deep as one problem, no traceback."""
    from rangeret.submission.nuscenes import validate_nuscenes_submission

    scans = _predict(tree, tmp_path / "pred")
    out = tmp_path / "results.zip"
    write_nuscenes_results(
        tmp_path / "pred", scans, out, profile=PROFILE, submission="[" * 30_000, description="d"
    )
    check = validate_nuscenes_submission(out, tree, "mini_val", profile=PROFILE, allow_partial=True)
    assert not check.ok
    assert any("submission.json is not JSON (it nests too deeply)" in p for p in check.problems)
