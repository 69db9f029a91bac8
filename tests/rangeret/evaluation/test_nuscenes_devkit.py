"""The project against nuScenes' own devkit (`nuscenes-devkit` 1.2.0, in a venv of its own that
`tests/support/devkit.py` builds once and caches): the devkit loads a simulated tree, its
`LidarSegEval` gives the numbers `rangeret evaluate` gives to 1e-9, its `validate_submission`
passes on the unpacked archive `rangeret submission` writes, and it refuses every archive the
project's validator refuses.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import pytest

from rangeret.cli.main import main
from rangeret.dataset.profiles import load_profile
from rangeret.models import save_checkpoint
from tests.support.devkit import run_devkit
from tests.support.nuscenes import network, refusals, small_profile, submit
from tests.support.nuscenes import write_tree as nuscenes_tree

pytestmark = pytest.mark.slow

#: Both mini_val scenes, whole (the devkit refuses a split it does not hold all of), and a
#: mini_train scene the split leaves out.
SCENES = {"scene-0103": 3, "scene-0916": 2, "scene-0061": 1}
VERSION = "v1.0-mini"


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return nuscenes_tree(tmp_path_factory.mktemp("nu"), SCENES)


@pytest.fixture(scope="module")
def predictions(tmp_path_factory: pytest.TempPathFactory, tree: Path) -> Path:
    folder = tmp_path_factory.mktemp("pred")
    weights = folder / "w.pt"
    save_checkpoint(weights, network(seed=3), profile=small_profile().to_dict())
    args = ["predict", "-q", "--dataset", str(tree), "--split", "mini_val"]
    assert main([*args, "--out", str(folder / "p"), "--checkpoint", str(weights)]) == 0
    return folder / "p"


def devkit(*args: str) -> dict:
    return run_devkit(*args)


def devkit_validate(tree: Path, folder: Path) -> dict:
    """The devkit's `validate_submission` of a results folder for mini_val."""
    args = ["--dataroot", str(tree), "--version", VERSION, "--results", str(folder)]
    return devkit("validate", *args, "--eval-set", "mini_val")


def unpack(archive: Path, folder: Path) -> Path:
    with zipfile.ZipFile(archive) as zf:
        zf.extractall(folder)
    return folder


def test_the_devkit_loads_the_simulated_tree(tree: Path) -> None:
    loaded = devkit("load", "--dataroot", str(tree), "--version", VERSION)
    assert loaded["scenes"] == list(SCENES)
    assert loaded["samples"] == loaded["lidarseg"] == sum(SCENES.values())
    names = load_profile("nuscenes").labels.raw_names
    assert {int(k): v for k, v in loaded["categories"].items()} == dict(names)


def test_evaluate_equals_lidarsegeval(tree: Path, predictions: Path, tmp_path: Path) -> None:
    theirs = devkit(
        "evaluate",
        "--dataroot",
        str(tree),
        "--version",
        VERSION,
        "--results",
        str(predictions),
        "--eval-set",
        "mini_val",
    )
    report = tmp_path / "r.json"
    args = ["evaluate", "-q", "--profile", "nuscenes", "--dataset", str(tree), "--split"]
    assert main([*args, "mini_val", "--predictions", str(predictions), "--json", str(report)]) == 0
    ours = json.loads(report.read_text())
    assert ours["miou"] == pytest.approx(theirs["miou"], abs=1e-9)
    assert ours["freq_weighted_iou"] == pytest.approx(theirs["freq_weighted_iou"], abs=1e-9)
    assert set(theirs["iou_per_class"]) == {"ignore", *ours["iou"]}
    assert theirs["iou_per_class"]["ignore"] is None
    defined = 0
    for name, value in ours["iou"].items():
        if theirs["iou_per_class"][name] is None:
            assert value is None, name
        else:
            defined += 1
            assert value == pytest.approx(theirs["iou_per_class"][name], abs=1e-9), name
    assert defined >= 5


def test_the_devkit_accepts_our_archive(tree: Path, predictions: Path, tmp_path: Path) -> None:
    archive = tmp_path / "s.zip"
    assert submit(tree, predictions, archive) == 0
    folder = unpack(archive, tmp_path / "unpacked")
    verdict = devkit_validate(tree, folder)
    assert verdict == {"ok": True}


def test_the_devkit_refuses_what_we_refuse(tree: Path, predictions: Path, tmp_path: Path) -> None:
    cases = refusals(tree, predictions, tmp_path)
    assert set(cases) == {"missing", "count", "zero", "seventeen", "flag"}
    for case, (archive, _) in cases.items():
        args = ["validate-submission", str(archive), "--profile", "nuscenes"]
        assert main([*args, "--dataset", str(tree), "--split", "mini_val"]) == 1, case
        folder = unpack(archive, tmp_path / f"unpacked-{case}")
        verdict = devkit_validate(tree, folder)
        assert verdict["ok"] is False, (case, verdict)
