"""`rangeret predict --profile TARGET --label-map MAP`: a network run on another sensor's dataset,
its own classes written as the target's raw ids, scored with `evaluate --profile TARGET` and shown
beside another report by `compare`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from rangeret.cli.main import main
from rangeret.dataset.label_map import load_label_map
from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.inference.predictor import Predictor
from rangeret.io.scans import read_labels
from rangeret.models import build_model, save_checkpoint

pytestmark = pytest.mark.slow

SOURCE = load_profile("semantickitti")
#: Raw ids the many-to-one map merges: other-vehicle and truck become car.
MERGED = {18: 10, 20: 10}


def _target(
    path: Path,
    *,
    name: str = "test-32",
    intensity: bool = False,
    splits: dict[str, list[str]] | None = None,
) -> Path:
    """A 32-beam sensor (+10 to -30 degrees, 32 x 256) with SemanticKITTI's labels in
    ROOT/scans/NNN; with `intensity`, 8-bit reflectance and each point's ring; `splits` replaces
    SemanticKITTI's."""
    data = SOURCE.to_dict()
    data["name"] = name
    data["sensor"].update(height=32, width=256, fov_up=10.0, fov_down=-30.0)
    data["layout"] = {"sequence_folders": ["scans"], "id_digits": 3}
    if splits is not None:
        data["splits"] = splits
    if intensity:
        data["points"] = {"fields": ["x", "y", "z", "intensity", "ring"]}
        data["sensor"].update(row="ring", reflectance_max=255.0)
    path.write_text(DatasetProfile.from_dict(data).to_yaml())
    return path


def _map(path: Path, merged: dict[int, int]) -> Path:
    """A label map of every SemanticKITTI raw id onto itself, but for the `merged` ones."""
    ids = sorted(SOURCE.labels.raw_to_class)
    path.write_text("".join(f"{i}: {merged.get(i, i)}\n" for i in ids))
    return path


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A network of the semantickitti profile, and a labelled dataset of the 32-beam sensor."""
    folder = tmp_path_factory.mktemp("other-sensor")
    target = _target(folder / "target.yaml")
    data = folder / "data"
    argv = ["simulate", "-q", "--out", str(data), "--profile", str(target), "--sequences", "1:2"]
    assert main([*argv, "--azimuth-steps", "512", "--seed", "3"]) == 0
    torch.manual_seed(0)
    network = build_model("rangeret-cir", 64, 256, num_classes=SOURCE.num_classes, layers=1)
    weights = folder / "w.pt"
    save_checkpoint(weights, network, profile=SOURCE.to_dict())
    return {"target": target, "data": data, "weights": weights, "folder": folder}


def _predict(setup: dict[str, Path], out: Path, *options: str) -> int:
    args = ["predict", "-q", "--dataset", str(setup["data"]), "--sequences", "1"]
    return main([*args, "--out", str(out), "--checkpoint", str(setup["weights"]), *options])


def test_without_a_map_another_profile_is_refused(setup, tmp_path, capsys):
    assert _predict(setup, tmp_path / "p", "--profile", str(setup["target"])) == 1
    assert "was trained for the semantickitti profile" in capsys.readouterr().err


def test_the_network_labels_the_other_sensors_scans_through_the_map(setup, tmp_path, capsys):
    identity, merged = _map(tmp_path / "same.yaml", {}), _map(tmp_path / "merged.yaml", MERGED)
    target = str(setup["target"])
    assert (
        _predict(setup, tmp_path / "same", "--profile", target, "--label-map", str(identity)) == 0
    )
    assert (
        _predict(setup, tmp_path / "merged", "--profile", target, "--label-map", str(merged)) == 0
    )

    scans = sorted((setup["data"] / "scans" / "001" / "velodyne").glob("*.bin"))
    assert len(scans) == 2
    lut = np.arange(1 << 16, dtype=np.uint32)
    lut[list(MERGED)] = list(MERGED.values())
    for scan in scans:
        points = np.fromfile(scan, np.float32).reshape(-1, 4)
        name = f"sequences/001/predictions/{scan.stem}.label"
        same, many = read_labels(tmp_path / "same" / name), read_labels(tmp_path / "merged" / name)
        assert same.shape == many.shape == (len(points),)
        assert set(np.unique(same)) <= set(SOURCE.labels.class_raw_ids)
        # The merged run writes exactly what the identity run wrote, through the map.
        assert np.array_equal(many, lut[same]) and not set(np.unique(many)) & set(MERGED)

    record = json.loads((tmp_path / "merged" / "run.json").read_text())
    assert record["profile"] == "test-32" and record["network_profile"] == "semantickitti"
    assert record["projection"]["height"] == 32 and record["projection"]["width"] == 256
    assert record["label_map"]["path"] == str(merged)
    assert record["label_map"]["mapping"]["18"] == 10
    assert record["runs"][-1]["label_map"] == record["label_map"]

    # Scored on the target's label set, and shown side by side.
    reports = []
    for run in ("same", "merged"):
        report = tmp_path / f"{run}.json"
        args = ["evaluate", "-q", "--dataset", str(setup["data"]), "--profile", target]
        assert (
            main(
                [
                    *args,
                    "--sequences",
                    "1",
                    "--predictions",
                    str(tmp_path / run),
                    "--json",
                    str(report),
                ]
            )
            == 0
        )
        reports.append(report)
    capsys.readouterr()
    assert main(["compare", *map(str, reports)]) == 0
    table = capsys.readouterr().out
    assert "car" in table and "mIoU" in table


def test_a_split_is_the_data_profiles(setup, tmp_path):
    """`--split` names a split of the data's profile, not of the network's."""
    target = _target(
        tmp_path / "t.yaml", splits={"train": ["000"], "valid": ["001"], "test": ["002"]}
    )
    identity = str(_map(tmp_path / "same.yaml", {}))
    args = ["predict", "-q", "--dataset", str(setup["data"]), "--split", "valid"]
    args += ["--out", str(tmp_path / "p"), "--checkpoint", str(setup["weights"])]
    assert main([*args, "--profile", str(target), "--label-map", identity]) == 0
    assert len(list((tmp_path / "p" / "sequences" / "001" / "predictions").glob("*.label"))) == 2


def test_the_reflectance_means_what_the_network_learnt(setup, tmp_path):
    """A sensor of 8-bit intensities gets the network's reflectance statistics in its scale."""
    network = Predictor.from_checkpoint(setup["weights"])
    plain = load_profile(_target(tmp_path / "r.yaml"))
    eight_bit = load_profile(_target(tmp_path / "i.yaml", name="test-32i", intensity=True))
    ids = _map(tmp_path / "m.yaml", {})
    on_plain = network.for_data(plain, load_label_map(ids, plain))
    on_eight_bit = network.for_data(eight_bit, load_label_map(ids, eight_bit))
    rng = np.random.default_rng(0)
    points = rng.normal(0, 10, (500, 4)).astype(np.float32)
    points[:, 3] = rng.uniform(0, 1, 500)
    scaled = np.column_stack([points[:, :3], points[:, 3] * 255, np.zeros(500)]).astype(np.float32)
    scaled[:, 4] = 31 - on_plain.project(points).proj_y.clip(0)
    a, b = on_plain.project(points), on_eight_bit.project(scaled)
    assert np.array_equal(a.mask, b.mask)
    np.testing.assert_allclose(a.image[4][a.mask], b.image[4][b.mask], atol=1e-5)
    assert on_eight_bit.profile.reflectance_fill == pytest.approx(SOURCE.reflectance_fill * 255)


@pytest.mark.parametrize(
    ("options", "problem"),
    [
        (["--label-map", "{map}"], "--label-map needs --profile naming the profile of the dataset"),
        (
            ["--profile", "{target}", "--label-map", "{partial}"],
            "raw id 10 (car, a class of the semantickitti profile the network can predict) is "
            "not in the label map",
        ),
    ],
)
def test_a_wrong_run_on_another_sensor_is_one_line(setup, tmp_path, capsys, options, problem):
    paths = {
        "map": _map(tmp_path / "m.yaml", {}),
        "target": setup["target"],
        "partial": tmp_path / "partial.yaml",
    }
    paths["partial"].write_text("0: 0\n1: 0\n")
    assert _predict(setup, tmp_path / "p", *(o.format(**paths) for o in options)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and problem in err[0]
    assert not (tmp_path / "p").exists()
