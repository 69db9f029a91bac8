"""`rangeret predict --panoptic`, `evaluate --panoptic`, `submission --task panoptic` and
`validate-submission --task panoptic` on a simulated SemanticKITTI dataset, judged by the
benchmark's own scripts: `evaluate_panoptic.py` gives the same scores, `validate_submission.py
--task panoptic` accepts the archive.

The network is a 1-block rangeret-cir with random weights at 32 x 256, saved with the
semantickitti profile at that resolution; the dataset is `rangeret simulate` at 32 beams: the
validation sequence 08 and one scan of each test sequence.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from rangeret.cli.main import main
from rangeret.dataset.layout import discover
from rangeret.dataset.profiles import load_profile
from rangeret.exceptions import InputError
from rangeret.inference.predictor import Predictor
from rangeret.inference.spec import InferenceSpec
from rangeret.models import build_model, save_checkpoint
from tests.support.paths import DATA, data_path

TEST_SEQUENCES = [f"{s}:1" for s in range(11, 22)]
SCORE_KEYS = (
    "pq_mean",
    "pq_dagger",
    "sq_mean",
    "rq_mean",
    "iou_mean",
    "pq_stuff",
    "rq_stuff",
    "sq_stuff",
    "pq_things",
    "rq_things",
    "sq_things",
)


def _network() -> torch.nn.Module:
    """Random weights wide enough that the argmax varies from pixel to pixel."""
    net = build_model("rangeret-cir", 32, 256, num_classes=20, layers=1).eval()
    g = torch.Generator().manual_seed(3)
    state = {
        k: torch.randn(v.shape, generator=g) * 0.5
        if v.is_floating_point() and not k.endswith("running_var")
        else v
        for k, v in net.state_dict().items()
    }
    net.load_state_dict(state)
    return net


def _profile():
    profile = load_profile("semantickitti")
    projection = dataclasses.replace(profile.projection, height=32, width=256)
    return dataclasses.replace(profile, projection=projection)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("kitti")
    args = ["simulate", "-q", "--out", str(root), "--sequences", "08:2", *TEST_SEQUENCES]
    assert main([*args, "--unlabelled", *(s.split(":")[0] for s in TEST_SEQUENCES)]) == 0
    return root


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "kitti32.pt"
    save_checkpoint(path, _network(), profile=_profile().to_dict())
    return path


def _predict(dataset: Path, checkpoint: Path, out: Path, *extra: str) -> None:
    args = ["predict", "-q", "--dataset", str(dataset), "--out", str(out)]
    sequences = ["08", *(s.split(":")[0] for s in TEST_SEQUENCES)]
    assert main([*args, "--sequences", *sequences, "--checkpoint", str(checkpoint), *extra]) == 0


@pytest.fixture(scope="module")
def semantic(tmp_path_factory: pytest.TempPathFactory, dataset: Path, checkpoint: Path) -> Path:
    out = tmp_path_factory.mktemp("semantic")
    _predict(dataset, checkpoint, out)
    return out


@pytest.fixture(scope="module")
def panoptic(tmp_path_factory: pytest.TempPathFactory, dataset: Path, checkpoint: Path) -> Path:
    out = tmp_path_factory.mktemp("panoptic")
    _predict(dataset, checkpoint, out, "--panoptic")
    return out


def _scans(dataset: Path) -> list:
    sequences = ["08", *(s.split(":")[0] for s in TEST_SEQUENCES)]
    return discover(dataset, sequences, layout=load_profile("semantickitti").layout).scans


def test_panoptic_labels_hold_the_semantic_labels_and_an_object_per_thing_point(
    dataset: Path, semantic: Path, panoptic: Path
) -> None:
    profile = load_profile("semantickitti")
    objects = 0
    for entry in _scans(dataset):
        sem = np.fromfile(semantic / entry.prediction, dtype="<u4")
        pan = np.fromfile(panoptic / entry.prediction, dtype="<u4")
        assert (pan & 0xFFFF).tobytes() == sem.tobytes(), entry.key
        instance = pan >> 16
        thing = np.isin(profile.labels.to_class(sem), profile.things)
        assert (instance[thing] > 0).all(), entry.key
        assert (instance[~thing] == 0).all(), entry.key
        objects += len(np.unique(instance[thing]))
    assert objects > len(_scans(dataset))
    run = json.loads((panoptic / "run.json").read_text())
    assert run["panoptic"] == {"angle": 10.0, "min_points": 10}
    assert "panoptic" not in json.loads((semantic / "run.json").read_text())


def test_a_semantic_tree_is_not_resumed_as_a_panoptic_one(
    dataset: Path, checkpoint: Path, semantic: Path, tmp_path: Path, capsys
) -> None:
    out = tmp_path / "tree"
    shutil.copytree(semantic, out)
    args = ["predict", "-q", "--dataset", str(dataset), "--out", str(out), "--sequences", "08"]
    assert main([*args, "--checkpoint", str(checkpoint), "--panoptic"]) == 1
    err = capsys.readouterr().err
    assert "holds semantic predictions and this run is panoptic" in err
    assert "Traceback" not in err


def _official_scores(dataset: Path, predictions: Path, tmp_path: Path, *extra: str) -> dict:
    """`evaluate_panoptic.py` of the SemanticKITTI development kit on the valid split."""
    kit = tmp_path / "kit"
    (kit / "auxiliary").mkdir(parents=True)
    reference = DATA / "reference"
    shutil.copy(reference / "semantic_kitti_evaluate_panoptic.py", kit / "evaluate_panoptic.py")
    shutil.copy(reference / "semantic_kitti_eval_np.py", kit / "auxiliary" / "eval_np.py")
    out = tmp_path / "official"
    out.mkdir()
    args = ["--dataset", str(dataset), "--predictions", str(predictions), "--split", "valid"]
    args += ["--data_cfg", str(data_path("semantic-kitti.yaml")), "--output", str(out)]
    proc = subprocess.run(
        [sys.executable, "evaluate_panoptic.py", *args, *extra],
        cwd=kit,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return yaml.safe_load((out / "scores.txt").read_text())


@pytest.mark.parametrize("min_points", [None, 10])
def test_evaluate_panoptic_equals_the_official_script(
    dataset: Path, panoptic: Path, tmp_path: Path, min_points: int | None
) -> None:
    extra = [] if min_points is None else ["--min_inst_points", str(min_points)]
    theirs = _official_scores(dataset, panoptic, tmp_path, *extra)
    report = tmp_path / "report.json"
    args = ["evaluate", "-q", "--dataset", str(dataset), "--predictions", str(panoptic)]
    args += ["--split", "valid", "--panoptic", "--json", str(report)]
    assert main(args + ([] if min_points is None else ["--min-points", str(min_points)])) == 0
    ours = json.loads(report.read_text())
    assert set(SCORE_KEYS) <= set(ours)
    for key in SCORE_KEYS:
        assert ours[key] == pytest.approx(theirs[key], abs=1e-9), key
    assert ours["min_points"] == (50 if min_points is None else min_points)
    assert set(ours["classes"]["car"]) == {"pq", "sq", "rq", "iou"}
    assert list(ours["per_sequence"]) == ["08"]
    assert ours["per_sequence"]["08"]["pq_mean"] == pytest.approx(ours["pq_mean"], abs=1e-12)
    assert len(ours["per_distance"]) == 6


def test_the_official_validator_accepts_the_panoptic_archive(
    dataset: Path, panoptic: Path, tmp_path: Path
) -> None:
    archive = tmp_path / "panoptic.zip"
    args = ["--dataset", str(dataset), "--allow-partial", "--task", "panoptic"]
    write = ["submission", "-q", "--predictions", str(panoptic), "--out", str(archive)]
    assert main([*write, *args]) == 0
    assert main(["validate-submission", "-q", str(archive), *args]) == 0
    proc = subprocess.run(
        [
            sys.executable,
            str(DATA / "reference" / "semantic_kitti_validate_submission.py"),
            str(archive),
            str(dataset),
            "--task",
            "panoptic",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stdout[-2000:]
    assert "Everything ready for submission" in proc.stdout


def test_a_semantic_archive_is_refused_as_a_panoptic_one(
    dataset: Path, semantic: Path, tmp_path: Path, capsys
) -> None:
    archive = tmp_path / "semantic.zip"
    common = ["--dataset", str(dataset), "--allow-partial"]
    args = ["submission", "-q", "--predictions", str(semantic), "--out", str(archive), *common]
    assert main(args) == 0
    assert main(["validate-submission", "-q", str(archive), *common, "--task", "panoptic"]) == 1
    err = capsys.readouterr().err
    assert "thing-class points has an instance: these are semantic labels" in err
    assert main(["validate-submission", "-q", str(archive), *common]) == 0


def test_a_profile_without_thing_classes_refuses_panoptic_in_one_sentence(
    dataset: Path, checkpoint: Path, tmp_path: Path, capsys
) -> None:
    pandaset = load_profile("pandaset")
    network = build_model("rangeret-cir", 32, 256, num_classes=pandaset.num_classes, layers=1)
    with pytest.raises(InputError, match="the pandaset profile names no thing classes"):
        Predictor.from_network(network, pandaset, InferenceSpec(panoptic=True))
    args = ["evaluate", "-q", "--dataset", str(dataset), "--predictions", str(tmp_path)]
    assert main([*args, "--sequences", "08", "--profile", "pandaset", "--panoptic"]) == 1
    err = capsys.readouterr().err
    assert "names no thing classes" in err and "Traceback" not in err


def test_a_panoptic_label_file_of_the_wrong_length_is_named(
    dataset: Path, panoptic: Path, tmp_path: Path, capsys
) -> None:
    out = tmp_path / "pred"
    shutil.copytree(panoptic, out)
    entry = next(e for e in _scans(dataset) if e.sequence == "08")
    path = out / entry.prediction
    path.write_bytes(path.read_bytes()[:-4])
    args = ["evaluate", "-q", "--dataset", str(dataset), "--predictions", str(out)]
    assert main([*args, "--sequences", "08", "--panoptic"]) == 1
    err = capsys.readouterr().err
    assert f"{path}: holds" in err and "but the scan has" in err and "Traceback" not in err


def test_a_scan_with_more_objects_than_its_label_holds_is_a_named_failure(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    profile = load_profile("nuscenes")
    network = build_model("rangeret-cir", 32, 256, num_classes=17, layers=1).eval()
    profile = dataclasses.replace(
        profile, projection=dataclasses.replace(profile.projection, width=256)
    )
    predictor = Predictor.from_network(network, profile, InferenceSpec(panoptic=True))
    car = profile.labels.class_names.index("car")

    def every_point_an_object(projection, classes):
        return np.arange(1, classes.size + 1, dtype=np.uint32)

    monkeypatch.setattr(predictor, "instances", every_point_an_object)
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-20, 20, (1500, 3)), rng.uniform(0, 255, 1500), np.zeros(1500)]
    projection = predictor.project(points.astype(np.float32))
    classes = np.full(projection.num_points, car)
    outcome = predictor.scan_prediction(projection, classes)
    assert outcome == (
        f"the scan has 1500 objects of class {car}; a nuScenes-panoptic label holds at most "
        "999 per class"
    )
