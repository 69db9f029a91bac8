"""A dataset job's split and version checked against its model's profile
(`service.jobs.selection`): each refusal a 400 naming the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from rangeret.dataset.profiles import load_profile
from service.jobs.errors import BadJobRequest
from service.jobs.selection import check_selection, dataset_version, incomplete_split
from service.routes.job_errors import job_error_answer
from service.schemas import DatasetJobRequest
from tests.support.apps import one_model

KITTI = one_model(load_profile("semantickitti")).default_entry
NU = one_model(load_profile("nuscenes"), name="nu").default_entry


def _refused(call, *args) -> str:
    with pytest.raises(BadJobRequest) as refused:
        call(*args)
    answer = job_error_answer(refused.value)
    assert answer.status_code == 400
    return answer.detail


def test_splits_are_the_profiles_own_names():
    check_selection(DatasetJobRequest(dataset="d", split="valid"), KITTI)
    for split in ("val", "mini_val", "mini_train", "test"):
        check_selection(DatasetJobRequest(dataset="d", split=split, version="v1.0-mini"), NU)
    nu = _refused(check_selection, DatasetJobRequest(dataset="d", split="valid"), NU)
    assert nu == (
        "The field 'split' is 'valid', which is not a split of the nuscenes profile of model "
        "nu: its splits are train, val, test, mini_train, mini_val (did you mean val?)."
    )
    kitti = _refused(check_selection, DatasetJobRequest(dataset="d", split="mini_val"), KITTI)
    assert kitti.startswith("The field 'split' is 'mini_val'") and "train, valid, test" in kitti


def test_a_version_is_refused_for_a_folder_layout():
    request = DatasetJobRequest(dataset="d", split="valid", version="v1.0-mini")
    detail = _refused(check_selection, request, KITTI)
    assert detail.startswith("The field 'version' is for datasets of a version's tables")
    assert "model default" in detail and "semantickitti" in detail


def _versions(root: Path, *names: str) -> Path:
    for name in names:
        (root / name).mkdir(parents=True)
        (root / name / "scene.json").write_text("[]")
    return root


def test_the_version_is_the_one_asked_for_or_the_one_held(tmp_path):
    one = _versions(tmp_path / "one", "v1.0-mini")
    two = _versions(tmp_path / "two", "v1.0-mini", "v1.0-test")
    assert dataset_version(one, None, NU) == "v1.0-mini"
    assert dataset_version(two, "v1.0-test", NU) == "v1.0-test"
    assert dataset_version(two, None, KITTI) is None
    assert _refused(dataset_version, two, None, NU) == (
        "The dataset holds the versions v1.0-mini, v1.0-test: choose one with the field 'version'."
    )
    absent = _refused(dataset_version, one, "v1.0-trainval", NU)
    assert absent.startswith("The field 'version' is 'v1.0-trainval'")
    assert absent.endswith("it holds v1.0-mini.")
    assert "no nuScenes version folder" in _refused(dataset_version, tmp_path, None, NU)


def test_an_incomplete_split_names_what_it_lacks():
    scenes = [f"scene-{i:04d}" for i in range(8)]
    assert incomplete_split("val", scenes, scenes[1:]) == (
        "The dataset holds 1 of the 8 sequences of the split 'val' (it lacks scene-0001, "
        "scene-0002, scene-0003, scene-0004, scene-0005 and 2 more): name those it holds with "
        "the field 'sequences'."
    )
