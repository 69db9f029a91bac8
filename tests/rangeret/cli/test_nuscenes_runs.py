"""`rangeret predict`, `evaluate`, `submission` and `validate-submission` on a simulated nuScenes
tree: predictions where the benchmark wants them, every value one it accepts, the devkit's
scores (written out here from its definition), and archives refused with one line per fault.

The network is a 1-block rangeret-cir with 17 classes and random weights at 32 x 256, saved
with the nuscenes profile; the tree is `rangeret simulate --profile nuscenes` at 256 columns.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from rangeret.cli.main import main
from rangeret.dataset.profiles import load_profile
from rangeret.inference.predictor import Predictor
from rangeret.models import save_checkpoint
from tests.support.nuscenes import (
    entries,
    network,
    refusals,
    small_profile,
    submit,
    write_tree,
)

SCENES = {"scene-0061": 2, "scene-0103": 2, "scene-0916": 1}


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tree(tmp_path_factory.mktemp("nu"), SCENES)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "nu17.pt"
    profile = small_profile()
    save_checkpoint(path, network(), profile=profile.to_dict())
    return path


@pytest.fixture(scope="module")
def predictions(tmp_path_factory: pytest.TempPathFactory, tree: Path, checkpoint: Path) -> Path:
    out = tmp_path_factory.mktemp("pred")
    args = ["predict", "-q", "--dataset", str(tree), "--split", "mini_val", "--out", str(out)]
    assert main([*args, "--checkpoint", str(checkpoint), "--save-confidence"]) == 0
    return out


def test_predict_writes_one_accepted_value_per_point(tree: Path, predictions: Path) -> None:
    found = entries(tree, ["scene-0103", "scene-0916"], with_labels=True)
    assert len(found) == 3
    files = sorted((predictions / "lidarseg" / "mini_val").iterdir())
    assert [f.name for f in files] == sorted(f"{e.name}_lidarseg.bin" for e in found)
    for entry in found:
        values = np.fromfile(predictions / entry.prediction, np.uint8)
        points = np.fromfile(entry.scan_path, np.float32).reshape(-1, 5)
        assert values.size == len(points)
        assert values.min() >= 1 and values.max() <= 16
        assert len(np.unique(values)) > 1
        confidence = np.load(predictions / "confidence" / "mini_val" / f"{entry.name}.npy")
        assert confidence.shape == (len(points),)
    record = json.loads((predictions / "run.json").read_text())
    assert record["runs"][-1]["profile"] == "nuscenes"


def test_named_scenes_go_to_their_split_and_runs_resume(
    tmp_path: Path, tree: Path, checkpoint: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["predict", "-q", "--dataset", str(tree), "--out", str(tmp_path)]
    args += ["--checkpoint", str(checkpoint), "--sequences", "scene-0061", "scene-0103"]
    assert main(args) == 0
    assert len(list((tmp_path / "lidarseg" / "mini_train").iterdir())) == 2
    assert len(list((tmp_path / "lidarseg" / "mini_val").iterdir())) == 2
    capsys.readouterr()
    assert main(args) == 0
    assert "0 written, 4 already done" in capsys.readouterr().out


def test_split_names_are_the_profiles(
    tree: Path, checkpoint: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["--dataset", str(tree), "--out", str(tmp_path), "--checkpoint", str(checkpoint)]
    assert main(["predict", "-q", *base, "--split", "valid"]) == 1
    err = capsys.readouterr().err
    assert "unknown split 'valid'" in err and "did you mean val?" in err
    assert "mini_train, mini_val" in err
    assert main(["predict", "-q", *base, "--split", "mini_train"]) == 1
    err = capsys.readouterr().err
    assert "scene-0553" in err and "--allow-partial" in err
    kitti = ["evaluate", "-q", "--dataset", str(tree), "--predictions", str(tmp_path)]
    assert main([*kitti, "--split", "val"]) == 1
    assert "did you mean valid?" in capsys.readouterr().err


def test_ignore_is_never_chosen_and_unprojected_points_get_their_class() -> None:
    """Even a head that favours ignore everywhere never outputs it, and a point at the origin
    (no pixel) gets the profile's unprojected class, one of 1..16."""
    profile = small_profile()
    net = network()
    with torch.no_grad():
        net.head.mlp2.bias[0] += 1000.0
    predictor = Predictor.from_network(net, profile)
    rng = np.random.default_rng(0)
    cloud = np.column_stack(
        [rng.uniform(-20, 20, (500, 3)), rng.uniform(0, 255, 500), rng.integers(0, 32, 500)]
    ).astype(np.float32)
    cloud[:3, :3] = 0.0
    result = predictor.predict(cloud)
    assert result.classes.min() >= 1 and result.labels.max() <= 16
    assert (result.labels[:3] == profile.unprojected_class).all()
    assert profile.unprojected_class == profile.labels.class_names.index("driveable_surface")


def devkit_scores(tree: Path, predictions: Path, scenes: list[str]) -> dict:
    """The devkit's mIoU, per-class IoU and frequency-weighted IoU, computed here from its
    definition: gt mapped general -> challenge class, ignore's row and column zeroed, IoU as
    intersection over a float32 union, NaN for an empty union, nanmean and nansum."""
    profile = load_profile("nuscenes")
    lut = np.array([profile.labels.raw_to_class[i] for i in range(32)])
    cm = np.zeros((17, 17), np.int64)
    for entry in entries(tree, scenes, with_labels=True):
        gt = lut[np.fromfile(entry.label_path, np.uint8)]
        pred = np.fromfile(predictions / entry.prediction, np.uint8)
        cm += np.bincount(17 * gt + pred, minlength=17 * 17).reshape(17, 17)
    cm[0, :] = 0
    cm[:, 0] = 0
    inter = np.diagonal(cm)
    union = cm.sum(1) + cm.sum(0) - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = inter / union.astype(np.float32)
    return {
        "iou": iou,
        "miou": float(np.nanmean(iou)),
        "fw": float(np.nansum(cm.sum(1) * iou) / cm.sum()),
    }


def test_evaluate_scores_as_the_devkit_defines(
    tree: Path, predictions: Path, tmp_path: Path
) -> None:
    report = tmp_path / "r.json"
    args = ["evaluate", "-q", "--profile", "nuscenes", "--dataset", str(tree)]
    args += ["--predictions", str(predictions), "--split", "mini_val", "--json", str(report)]
    assert main([*args, "--plots", str(tmp_path / "plots")]) == 0
    got = json.loads(report.read_text())
    want = devkit_scores(tree, predictions, ["scene-0103", "scene-0916"])
    assert got["miou"] == pytest.approx(want["miou"], abs=1e-12)
    assert got["freq_weighted_iou"] == pytest.approx(want["fw"], abs=1e-12)
    names = load_profile("nuscenes").labels.class_names
    for c in range(1, 17):
        value = got["iou"][names[c]]
        if np.isnan(want["iou"][c]):
            assert value is None
        else:
            assert value == pytest.approx(float(want["iou"][c]), abs=1e-12)
    assert set(got["per_sequence"]) == {"scene-0103", "scene-0916"}
    assert len(list((tmp_path / "plots").glob("*.png"))) == 5  # calibration too


def test_evaluate_names_a_value_the_benchmark_refuses(
    tree: Path, predictions: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(predictions, bad)
    entry = entries(tree, ["scene-0916"])[0]
    values = np.fromfile(bad / entry.prediction, np.uint8)
    values[7] = 0
    values.tofile(bad / entry.prediction)
    args = ["evaluate", "-q", "--profile", "nuscenes", "--dataset", str(tree)]
    assert main([*args, "--predictions", str(bad), "--split", "mini_val"]) == 1
    err = capsys.readouterr().err
    assert f"{entry.name}_lidarseg.bin: holds 1 value(s) outside the classes 1..16" in err
    assert "the first 0 at point 7" in err


def test_submission_is_the_results_folder(
    tree: Path, predictions: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "s.zip"
    assert submit(tree, predictions, out, "--use-map") == 0
    with zipfile.ZipFile(out) as zf:
        names = zf.namelist()
        meta = json.loads(zf.read("mini_val/submission.json"))
        description = zf.read("description.txt").decode()
    bins = [n for n in names if n.startswith("lidarseg/mini_val/") and n.endswith(".bin")]
    assert len(bins) == 3
    assert {"lidarseg/", "lidarseg/mini_val/", "mini_val/"} <= set(names)
    assert meta["meta"] == {
        "use_camera": False,
        "use_lidar": True,
        "use_radar": False,
        "use_map": True,
        "use_external": False,
    }
    run = json.loads((predictions / "run.json").read_text())["runs"][-1]
    assert meta["method"]["name"] == "RangeRet"
    assert meta["method"]["checkpoint_sha256"] == run["checkpoint_sha256"]
    assert description.startswith("name: RangeRet\n")
    assert run["checkpoint_sha256"] in description
    capsys.readouterr()
    args = ["validate-submission", str(out), "--profile", "nuscenes", "--dataset", str(tree)]
    assert main([*args, "--split", "mini_val"]) == 0
    assert "valid archive; 3 predictions checked" in capsys.readouterr().out


def test_each_fault_is_one_line(
    tree: Path, predictions: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for case, (archive, line) in refusals(tree, predictions, tmp_path).items():
        capsys.readouterr()
        args = ["validate-submission", str(archive), "--profile", "nuscenes"]
        assert main([*args, "--dataset", str(tree), "--split", "mini_val"]) == 1, case
        err = capsys.readouterr().err
        assert line in err and err.count(line) == 1, (case, err)


def test_a_partial_test_split_is_refused(tmp_path: Path, checkpoint: Path) -> None:
    root = write_tree(tmp_path / "test", {"scene-0077": 2}, labelled=False, version="v1.0-test")
    pred = tmp_path / "p"
    args = ["predict", "-q", "--dataset", str(root), "--sequences", "scene-0077"]
    assert main([*args, "--out", str(pred), "--checkpoint", str(checkpoint)]) == 0
    assert len(list((pred / "lidarseg" / "test").iterdir())) == 2
    sub = ["submission", "-q", "--profile", "nuscenes", "--dataset", str(root)]
    sub += ["--predictions", str(pred), "--out", str(tmp_path / "t.zip")]
    assert main(sub) == 1
    assert not (tmp_path / "t.zip").exists()
    assert main([*sub, "--allow-partial"]) == 0
    with zipfile.ZipFile(tmp_path / "t.zip") as zf:
        assert len([n for n in zf.namelist() if n.endswith("_lidarseg.bin")]) == 2


def test_view_shows_a_sweep_with_its_labels(
    tree: Path, predictions: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    entry = entries(tree, ["scene-0916"], with_labels=True)[0]
    out = tmp_path / "v.png"
    args = ["view", str(entry.scan_path), "--profile", "nuscenes", "--out", str(out)]
    assert main([*args, "--labels", str(predictions / entry.prediction)]) == 0
    assert out.read_bytes()[:4] == b"\x89PNG"
    assert "coloured by the prediction" in capsys.readouterr().out
    truth = np.fromfile(entry.label_path, np.uint8)
    short = tmp_path / "short.bin"
    truth[:-1].tofile(short)
    assert main([*args, "--ground-truth", str(short)]) == 1
    assert "(a label file holds one uint8 per point)" in capsys.readouterr().err


def test_a_root_of_two_versions_needs_version(
    tmp_path: Path, checkpoint: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    root = write_tree(tmp_path / "two", {"scene-0103": 1, "scene-0916": 1})
    shutil.copytree(root / "v1.0-mini", root / "v1.0-test")
    args = ["predict", "-q", "--dataset", str(root), "--split", "mini_val"]
    args += ["--out", str(tmp_path / "p"), "--checkpoint", str(checkpoint)]
    assert main(args) == 1
    assert "holds the versions v1.0-mini, v1.0-test: choose one with --version" in (
        capsys.readouterr().err
    )
    assert main([*args, "--version", "v1.0-mini"]) == 0
    assert len(list((tmp_path / "p" / "lidarseg" / "mini_val").iterdir())) == 2


#: Bytes of the oversized members below: each compresses to about 0.6 MB.
HUGE = 600 << 20
#: Resident memory a refusal may take beyond the command's own (torch and the tables).
MEMORY_ALLOWANCE = 200 << 20


def _validate_memory(archive: Path, tree: Path) -> tuple[int, str, int]:
    """`rangeret validate-submission` of `archive` in its own process: exit code, what it
    printed and its peak resident bytes."""
    import subprocess
    import sys

    from tests.support.paths import REPO

    measured = (
        "import resource, sys; from rangeret.cli.main import main; code = main(sys.argv[1:]); "
        "print('PEAK', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr); "
        "sys.exit(code)"
    )
    args = ["validate-submission", str(archive), "--profile", "nuscenes"]
    args += ["--dataset", str(tree), "--split", "mini_val"]
    done = subprocess.run(
        [sys.executable, "-c", measured, *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    peak = int(done.stderr.rsplit("PEAK", 1)[1].split()[0]) * 1024
    return done.returncode, done.stdout + done.stderr, peak


@pytest.mark.slow
def test_oversized_members_are_refused_by_their_declared_size(
    tree: Path, predictions: Path, tmp_path: Path
) -> None:
    """A prediction file, submission.json or description.txt declaring far more bytes than it
    may hold is refused (or, for the description, not read) before a byte of it is read."""
    good = tmp_path / "good.zip"
    assert submit(tree, predictions, good) == 0
    code, _, baseline = _validate_memory(good, tree)
    assert code == 0
    with zipfile.ZipFile(good) as zf:
        members = {i.filename: zf.read(i) for i in zf.infolist()}
    label = next(n for n in members if n.endswith("_lidarseg.bin"))
    cases = {
        label: f"{label} is {HUGE:,} bytes, more than the",
        "mini_val/submission.json": f"mini_val/submission.json is {HUGE:,} bytes, more than the",
        "description.txt": f"description.txt is {HUGE:,} bytes, more than the 65,536 read of it",
    }
    for member, words in cases.items():
        archive = tmp_path / "huge.zip"
        with zipfile.ZipFile(archive, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for name, data in members.items():
                zf.writestr(name, bytes(HUGE) if name == member else data)
        code, err, peak = _validate_memory(archive, tree)
        assert words in err, err
        assert code == (0 if member == "description.txt" else 1), err
        assert peak < baseline + MEMORY_ALLOWANCE, (member, peak, baseline)
