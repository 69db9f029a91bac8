"""`rangeret predict --panoptic`, `evaluate --panoptic` and `submission --task panoptic` on a
simulated nuScenes tree with its panoptic table: nuScenes-panoptic's files where the devkit looks
for them, its scores equal to the devkit's own `NuScenesPanopticEval` (run in its venv), and
archives refused with one line per fault.

The network is the 1-block rangeret-cir of `tests.support.nuscenes` (17 classes, random weights,
32 x 256).
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.cli.main import main
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.projection import project_with
from rangeret.inference.instances import row_gaps, scan_instances
from rangeret.inference.settings import ClusterSettings
from rangeret.io.panoptic_labels import PANOPTIC_NPZ, THOUSANDS, read_panoptic_npz
from rangeret.io.scans import read_scan
from rangeret.models import save_checkpoint
from tests.support.devkit import run_devkit
from tests.support.nuscenes import entries, network, rewrite, small_profile, write_tree

SCENES = {"scene-0061": 1, "scene-0103": 2, "scene-0916": 2}
VAL = ["scene-0103", "scene-0916"]


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tree(tmp_path_factory.mktemp("nu"), SCENES)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "nu17.pt"
    save_checkpoint(path, network(seed=2), profile=small_profile().to_dict())
    return path


def _predict(tree: Path, checkpoint: Path, out: Path, *extra: str) -> Path:
    args = ["predict", "-q", "--dataset", str(tree), "--split", "mini_val", "--out", str(out)]
    assert main([*args, "--checkpoint", str(checkpoint), *extra]) == 0
    return out


@pytest.fixture(scope="module")
def semantic(tmp_path_factory: pytest.TempPathFactory, tree: Path, checkpoint: Path) -> Path:
    return _predict(tree, checkpoint, tmp_path_factory.mktemp("sem"))


@pytest.fixture(scope="module")
def panoptic(tmp_path_factory: pytest.TempPathFactory, tree: Path, checkpoint: Path) -> Path:
    return _predict(tree, checkpoint, tmp_path_factory.mktemp("pan"), "--panoptic")


def test_predictions_are_the_challenge_files(tree: Path, semantic: Path, panoptic: Path) -> None:
    profile = load_profile("nuscenes")
    found = entries(tree, VAL)
    names = sorted(p.name for p in (panoptic / "panoptic" / "mini_val").iterdir())
    assert names == sorted(f"{e.name}_panoptic.npz" for e in found)
    assert not (panoptic / "lidarseg").exists()
    for entry in found:
        classes = np.fromfile(
            semantic / "lidarseg" / "mini_val" / f"{entry.name}_lidarseg.bin", "u1"
        )
        with np.load(panoptic / "panoptic" / "mini_val" / f"{entry.name}_panoptic.npz") as npz:
            assert list(npz.keys()) == ["data"]
            values = npz["data"]
        assert values.dtype == np.uint16
        assert (values // 1000 == classes).all()
        instance = values % 1000
        thing = np.isin(classes, profile.things)
        assert (instance[thing] > 0).all() and (instance[~thing] == 0).all()
        for cls in np.unique(classes[thing]):
            numbers = np.unique(instance[classes == cls])
            assert list(numbers) == list(range(1, len(numbers) + 1))


def test_a_tree_without_the_panoptic_table_is_refused_naming_it(
    tmp_path: Path, checkpoint: Path, panoptic: Path, capsys
) -> None:
    tree = tmp_path / "nu"
    write_tree(tree, {"scene-0103": 1})
    (tree / "v1.0-mini" / "panoptic.json").unlink()
    args = ["evaluate", "-q", "--profile", "nuscenes", "--dataset", str(tree)]
    assert main([*args, "--predictions", str(panoptic), "--sequences", "scene-0103", "--panoptic"])
    err = capsys.readouterr().err
    assert "panoptic.json has no record for sweep" in err and "Traceback" not in err


@pytest.fixture(scope="module")
def oracle(tmp_path_factory: pytest.TempPathFactory, tree: Path) -> Path:
    """Panoptic files of the ground truth's classes, their objects found by the clustering: what
    the clustering scores with perfect semantics."""
    out = tmp_path_factory.mktemp("oracle")
    profile = small_profile()
    for entry in entries(tree, VAL, with_labels=True):
        points = read_scan(entry.scan_path, record=profile.points)
        classes = profile.labels.to_class(entry.label_file.read(entry.label_path))
        projection = project_with(points, profile.projection)
        instances = scan_instances(
            projection, points, classes, profile.things, row_gaps(profile), ClusterSettings()
        )
        values = THOUSANDS.encode(classes, instances, classes)
        PANOPTIC_NPZ.write(out / "panoptic" / "mini_val" / f"{entry.name}_panoptic.npz", values)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("min_points", [None, 5])
@pytest.mark.parametrize("which", ["network", "oracle"])
def test_evaluate_panoptic_equals_the_devkit(
    tree: Path,
    panoptic: Path,
    oracle: Path,
    tmp_path: Path,
    min_points: int | None,
    which: str,
) -> None:
    predictions = oracle if which == "oracle" else panoptic
    report = tmp_path / "report.json"
    args = ["evaluate", "-q", "--profile", "nuscenes", "--dataset", str(tree)]
    args += ["--predictions", str(predictions), "--split", "mini_val", "--panoptic"]
    extra = [] if min_points is None else ["--min-points", str(min_points)]
    assert main([*args, "--json", str(report), *extra]) == 0
    ours = json.loads(report.read_text())
    devkit_extra = [] if min_points is None else ["--min-inst-points", str(min_points)]
    theirs = run_devkit(
        "panoptic-evaluate",
        "--dataroot",
        tree,
        "--version",
        "v1.0-mini",
        "--results",
        predictions,
        "--eval-set",
        "mini_val",
        *devkit_extra,
    )
    assert ours["min_points"] == (15 if min_points is None else min_points)
    assert list(theirs) == [k for k in ours if k in theirs]
    for name, scores in theirs.items():
        assert list(ours[name]) == list(scores), name
        for key, value in scores.items():
            assert ours[name][key] == pytest.approx(value, abs=1e-9), (name, key)
    if which == "oracle":
        assert 0.2 < theirs["all"]["PQ"] < 1 and theirs["all"]["mIoU"] > 0.5


def _archive(tree: Path, predictions: Path, out: Path, *extra: str) -> int:
    args = ["submission", "-q", "--profile", "nuscenes", "--dataset", str(tree), "--task"]
    args += ["panoptic", "--predictions", str(predictions), "--out", str(out)]
    return main([*args, "--split", "mini_val", *extra])


def _validate(tree: Path, archive: Path) -> int:
    args = ["validate-submission", "-q", str(archive), "--profile", "nuscenes", "--task"]
    return main([*args, "panoptic", "--dataset", str(tree), "--split", "mini_val"])


def test_the_panoptic_archive_and_each_fault_refused(
    tree: Path, panoptic: Path, semantic: Path, tmp_path: Path, capsys
) -> None:
    good = tmp_path / "good.zip"
    assert _archive(tree, panoptic, good, "--use-map") == 0
    with zipfile.ZipFile(good) as zf:
        names = zf.namelist()
        meta = json.loads(zf.read("mini_val/submission.json"))["meta"]
    assert names[:3] == ["panoptic/", "panoptic/mini_val/", "mini_val/"]
    assert meta["task"] == "segmentation" and meta["use_map"] is True
    assert _validate(tree, good) == 0
    entry = entries(tree, ["scene-0103"])[0]
    name = f"panoptic/mini_val/{entry.name}_panoptic.npz"
    values = read_panoptic_npz(panoptic / name)
    short, other = io.BytesIO(), io.BytesIO()
    np.savez(short, data=values[:-1])
    np.savez(other, labels=values)
    cases = {
        "missing": ({name: None}, f"{name} does not exist"),
        "count": ({name: short.getvalue()}, f"holds {values.size - 1:,} panoptic values"),
        "no data": ({name: other.getvalue()}, "holds no array 'data'"),
        "task": (
            {"mini_val/submission.json": json.dumps({"meta": {**meta, "task": "tracking"}})},
            'meta.task must be "segmentation", got "tracking"',
        ),
    }
    for case, (change, line) in cases.items():
        capsys.readouterr()
        bad = rewrite(good, tmp_path / f"{case.replace(' ', '-')}.zip", change)
        assert _validate(tree, bad) == 1, case
        err = capsys.readouterr().err
        assert line in err, (case, err)
        assert "Traceback" not in err
    objectless = tmp_path / "objectless"
    for entry in entries(tree, VAL):
        classes = np.fromfile(
            semantic / "lidarseg" / "mini_val" / f"{entry.name}_lidarseg.bin", "u1"
        )
        target = objectless / "panoptic" / "mini_val" / f"{entry.name}_panoptic.npz"
        target.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(target, data=classes.astype(np.uint16) * 1000)
    assert _archive(tree, objectless, tmp_path / "objectless.zip") == 1
    assert "these are semantic labels, not panoptic ones" in capsys.readouterr().err
