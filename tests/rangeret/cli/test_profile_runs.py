"""`rangeret predict` on every built-in profile, point for point against the published pipeline.

For each dataset the test writes its own reading of the release's inference, straight from the
profile's facts and independent of the project's modules: the spherical projection (rows from the
pitch, or from PandaSet's laser id), normalisation with the profile's means and stds, the
network's argmax, the kNN vote with the dataset's rule (PandaSet lets class 0, car, win), and the
inverse label map. Inputs: a published-format state_dict with the profile's class count (random
weights) and a small simulated tree in the profile's own layout and point record.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml

from rangeret.cli.main import main
from rangeret.dataset.layout import discover, prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.inference.knn import gaussian_kernel
from rangeret.models import build_model, save_checkpoint
from rangeret.sim import SensorConfig, simulate_dataset

PROFILES = ("semantickitti", "semantic-poss", "pandaset")
WIDTH = 128
AZIMUTH_STEPS = 384


def _tree(root, profile):
    """Two labelled scans in sequence 1 and one unlabelled in sequence 8, in the profile's layout."""
    sensor = SensorConfig.for_profile(profile, azimuth_steps=AZIMUTH_STEPS)
    simulate_dataset(root, {"1": 2, "8": 1}, labelled=["1"], sensor=sensor, seed=5, profile=profile)
    return root


def _weights(path, profile, seed=0):
    """A published-format file: the bare state_dict of a 1-block rangeret-cir with the profile's
    class count, every weight drawn at random (wide enough that the argmax varies from pixel to
    pixel), BatchNorm variances kept."""
    network = build_model(
        "rangeret-cir", profile.projection.height, WIDTH, num_classes=profile.num_classes, layers=1
    )
    g = torch.Generator().manual_seed(seed)
    state = {
        k: torch.randn(v.shape, generator=g) * 0.5
        if v.is_floating_point() and not k.endswith("running_var")
        else v
        for k, v in network.state_dict().items()
    }
    torch.save(state, path)
    return network, state


def _predict_sequence_1(tmp_path, data, *options):
    """`rangeret predict` of sequence 1 of `data` into tmp_path/p; the exit code."""
    args = ["predict", "-q", "--dataset", str(data), "--sequences", "1"]
    return main([*args, "--out", str(tmp_path / "p"), *options])


def _reference_projection(points, spec, height, width):
    """The release's projection: (5, H, W) normalised image, each point's pixel and range."""
    sensor = spec["sensor"]
    xyz, remission = points[:, :3], points[:, 3]
    depth = np.linalg.norm(xyz, 2, axis=1)
    n = len(points)
    proj_x = np.full(n, -1, np.int64)
    proj_y = np.full(n, -1, np.int64)
    valid = np.isfinite(depth) & (depth > 0)
    idx = np.flatnonzero(valid)
    x, y, z, d = xyz[idx, 0], xyz[idx, 1], xyz[idx, 2], depth[idx]
    fov_up = abs(sensor["fov_up"]) / 180.0 * np.pi
    fov_down = abs(sensor["fov_down"]) / 180.0 * np.pi
    fov = np.float32(fov_up + fov_down)
    yaw = -np.arctan2(y, x)
    u = np.float32(0.5) * (yaw / np.float32(np.pi) + np.float32(1.0)) * np.float32(width)
    u = np.clip(np.floor(u), 0, width - 1).astype(np.int64)
    if sensor["row"] == "laser_id":
        v = points[idx, 4].astype(np.int32).astype(np.int64)
    else:
        pitch = np.arcsin(z / d)
        v = (np.float32(1.0) - (pitch + np.float32(fov_down)) / fov) * np.float32(height)
        v = np.clip(np.floor(v), 0, height - 1).astype(np.int64)
    proj_x[idx], proj_y[idx] = u, v
    # Farthest first, so that the closest point is written last; equal depths: lowest index last.
    order = np.lexsort((-idx, -d))
    proj_range = np.full((height, width), -1, np.float32)
    channels = np.zeros((5, height, width), np.float32)
    proj_range[v[order], u[order]] = d[order]
    values = np.stack([d, x, y, z, remission[idx]])[:, order]
    means = np.array(sensor["means"], np.float32)[:, None]
    stds = np.array(sensor["stds"], np.float32)[:, None]
    channels[:, v[order], u[order]] = (values - means) / stds
    channels[:, proj_range < 0] = 0
    unproj = np.zeros(n, np.float32)
    unproj[idx] = d
    return channels, proj_range, proj_x, proj_y, unproj


def _reference_knn(proj_range, argmax, proj_x, proj_y, unproj, votes_from, unlabeled, classes):
    """The release's kNN (k 7, window 7, sigma 1, cutoff 1) over classes votes_from..C-1."""
    k, search, cutoff = 7, 7, 1.0
    pad = search // 2
    ranges = np.pad(np.where(proj_range < 0, np.float32(np.inf), proj_range), pad)
    labels = np.pad(argmax, pad)
    weights = (1 - gaussian_kernel(search, 1.0).numpy()).reshape(-1)
    centre = search * search // 2
    out = np.full(len(proj_x), unlabeled, np.int64)
    for point in np.flatnonzero(proj_x >= 0):
        y, x = proj_y[point], proj_x[point]
        window = ranges[y : y + search, x : x + search].reshape(-1).copy()
        window[centre] = unproj[point]
        dist = (np.abs(window - unproj[point]) * weights).astype(np.float32)
        rank = dist.copy()
        rank[centre] = -1
        nearest = np.argsort(rank, kind="stable")[:k]
        nearest = nearest[dist[nearest] <= cutoff]
        votes = np.bincount(
            labels[y : y + search, x : x + search].reshape(-1)[nearest], minlength=classes
        )
        out[point] = votes[votes_from:].argmax() + votes_from
    return out


def reference_labels(scan_path, spec, state, height, width):
    """Raw labels of one scan by the release's pipeline, from the profile's plain data."""
    fields = len(spec["points"]["fields"])
    points = np.fromfile(scan_path, dtype=np.float32).reshape(-1, fields)
    image, proj_range, proj_x, proj_y, unproj = _reference_projection(points, spec, height, width)
    classes = len(spec["labels"]["classes"])
    network = build_model("rangeret-cir", height, width, num_classes=classes, layers=1)
    network.load_state_dict(state)
    with torch.inference_mode():
        argmax = network.eval()(torch.from_numpy(image)[None])[0].argmax(0).numpy()
    unlabeled = spec["labels"]["unlabeled_class"]
    point_classes = _reference_knn(
        proj_range, argmax, proj_x, proj_y, unproj, spec["knn"]["votes_from"], unlabeled, classes
    )
    inverse = np.array([c["raw_id"] for c in spec["labels"]["classes"]], np.uint32)
    return inverse[point_classes]


@pytest.mark.parametrize("name", PROFILES)
def test_predict_gives_the_published_pipelines_labels_on_every_point(name, tmp_path, capsys):
    profile = load_profile(name)
    data = _tree(tmp_path / "data", profile)
    _, state = _weights(tmp_path / "w.pt", profile)
    height = profile.projection.height
    args = ["predict", "-q", "--dataset", str(data), "--sequences", "1", "8", "--out"]
    args += [str(tmp_path / "pred"), "--profile", name, "--checkpoint", str(tmp_path / "w.pt")]
    assert main([*args, "--width", str(WIDTH)]) == 0, capsys.readouterr().err
    spec = yaml.safe_load(profile.to_yaml())
    entries = discover(
        data, ["01", "08"] if name != "pandaset" else ["001", "008"], layout=profile.layout
    ).scans
    assert len(entries) == 3
    points = agree = 0
    for entry in entries:
        written = np.fromfile(
            prediction_path(tmp_path / "pred", entry.sequence, entry.name), np.uint32
        )
        expected = reference_labels(entry.scan_path, spec, state, height, WIDTH)
        points += expected.size
        agree += int((written == expected).sum())
    assert agree == points
    assert len(np.unique(written)) >= 3
    run = json.loads((tmp_path / "pred" / "run.json").read_text())
    assert run["profile"] == name and run["projection"]["height"] == height


def test_pandaset_ids_are_three_digits_and_class_0_is_car(tmp_path):
    profile = load_profile("pandaset")
    data = _tree(tmp_path / "data", profile)
    assert sorted(p.name for p in data.iterdir() if (p / "velodyne").is_dir()) == ["001", "008"]
    assert profile.labels.class_names[0] == "car" and profile.labels.class_raw_ids[14] == 0
    assert profile.labels.unlabeled_class == 14 and profile.labels.ignored[14]


def test_a_class_count_that_differs_from_the_profile_is_refused(tmp_path, capsys):
    panda = load_profile("pandaset")
    data = _tree(tmp_path / "data", load_profile("semantickitti"))
    _weights(tmp_path / "w.pt", panda)
    code = _predict_sequence_1(
        tmp_path, data, "--checkpoint", str(tmp_path / "w.pt"), "--width", str(WIDTH)
    )
    err = capsys.readouterr().err
    assert code == 1 and "15 classes" in err and "semantickitti profile has 20" in err
    assert "Traceback" not in err and not (tmp_path / "p" / "sequences").exists()


def test_a_profile_file_equal_to_a_builtin_gives_identical_labels(tmp_path):
    profile = load_profile("semantic-poss")
    data = _tree(tmp_path / "data", profile)
    _weights(tmp_path / "w.pt", profile)
    shown = subprocess.run(
        [sys.executable, "-m", "rangeret.cli.main", "profile", "show", "semantic-poss"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    (tmp_path / "poss.yaml").write_text(shown)
    base = ["predict", "-q", "--dataset", str(data), "--sequences", "1", "8"]
    base += ["--checkpoint", str(tmp_path / "w.pt"), "--width", str(WIDTH)]
    assert main([*base, "--out", str(tmp_path / "a"), "--profile", "semantic-poss"]) == 0
    assert (
        main([*base, "--out", str(tmp_path / "b"), "--profile", str(tmp_path / "poss.yaml")]) == 0
    )
    a = sorted((tmp_path / "a").rglob("*.label"))
    b = sorted((tmp_path / "b").rglob("*.label"))
    assert len(a) == 3 and [p.read_bytes() for p in a] == [p.read_bytes() for p in b]


def test_the_projects_checkpoints_run_only_with_their_profile(tmp_path, capsys):
    panda = load_profile("pandaset")
    data = _tree(tmp_path / "data", panda)
    network = build_model("rangeret-cir", 64, WIDTH, num_classes=15, layers=1)
    profile = panda.with_overrides(width=WIDTH)
    save_checkpoint(
        tmp_path / "own.pt",
        network,
        label_config=profile.labels,
        projection=profile.projection,
        profile=profile.to_dict(),
    )
    base = ["predict", "-q", "--dataset", str(data), "--sequences", "1", "--checkpoint"]
    base += [str(tmp_path / "own.pt")]
    assert main([*base, "--out", str(tmp_path / "p")]) == 0
    assert json.loads((tmp_path / "p" / "run.json").read_text())["profile"] == "pandaset"
    assert len(list((tmp_path / "p" / "sequences" / "001").rglob("*.label"))) == 2
    assert main([*base, "--out", str(tmp_path / "q"), "--profile", "semantickitti"]) == 1
    err = capsys.readouterr().err
    assert "trained for the pandaset profile" in err and "semantickitti" in err


def test_a_profile_without_demo_weights_asks_for_a_checkpoint(tmp_path, capsys):
    data = _tree(tmp_path / "data", load_profile("pandaset"))
    code = _predict_sequence_1(tmp_path, data, "--profile", "pandaset")
    err = capsys.readouterr().err
    assert code == 1 and "pass --checkpoint with a network for the pandaset profile" in err


def test_a_laser_id_off_the_image_names_the_file(tmp_path, capsys):
    profile = load_profile("pandaset")
    data = _tree(tmp_path / "data", profile)
    _weights(tmp_path / "w.pt", profile)
    scan = sorted((data / "001" / "velodyne").glob("*.bin"))[0]
    points = np.fromfile(scan, np.float32).reshape(-1, 5)
    points[np.flatnonzero(np.linalg.norm(points[:, :3], axis=1) > 0)[0], 4] = 64
    points.tofile(scan)
    code = _predict_sequence_1(
        tmp_path,
        data,
        "--profile",
        "pandaset",
        "--checkpoint",
        str(tmp_path / "w.pt"),
        "--width",
        str(WIDTH),
    )
    out, err = capsys.readouterr()
    assert code == 1 and "1 of 2 scans could not be predicted" in err
    assert f"FAILED 001/{scan.stem}: {scan}: 1 point(s) have a laser id outside" in out
    assert "rows 0..63" in out
    assert len(list((tmp_path / "p").rglob("*.label"))) == 1


def test_a_four_float_file_is_not_read_as_pandaset(tmp_path, capsys):
    profile = load_profile("pandaset")
    data = _tree(tmp_path / "data", profile)
    _weights(tmp_path / "w.pt", profile)
    scan = sorted((data / "001" / "velodyne").glob("*.bin"))[0]
    scan.write_bytes(np.zeros((7, 4), np.float32).tobytes())
    code = _predict_sequence_1(
        tmp_path,
        data,
        "--profile",
        "pandaset",
        "--checkpoint",
        str(tmp_path / "w.pt"),
        "--width",
        str(WIDTH),
    )
    out = "".join(capsys.readouterr())
    assert code == 1 and "not a multiple of 20" in out and "laser_id" in out


def test_pandaset_evaluation_ignores_class_14_not_car(tmp_path, capsys):
    profile = load_profile("pandaset")
    data = _tree(tmp_path / "data", profile)
    for entry in discover(data, ["001"], layout=profile.layout).scans:
        truth = np.fromfile(entry.label_path, np.uint32)
        out = prediction_path(tmp_path / "pred", entry.sequence, entry.name)
        out.parent.mkdir(parents=True, exist_ok=True)
        truth.tofile(out)
    args = ["evaluate", "-q", "--dataset", str(data), "--predictions", str(tmp_path / "pred")]
    code = main(
        [*args, "--sequences", "1", "--profile", "pandaset", "--json", str(tmp_path / "r.json")]
    )
    assert code == 0, capsys.readouterr().err
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["profile"] == "pandaset" and report["accuracy"] == 1.0
    assert "car" in report["iou"] and "unlabeled" not in report["iou"] and len(report["iou"]) == 14
    assert report["iou"]["car"] == 1.0


def test_submission_archives_are_the_benchmarks_only(tmp_path, capsys):
    args = ["submission", "--predictions", str(tmp_path), "--dataset", str(tmp_path)]
    code = main([*args, "--out", str(tmp_path / "s.zip"), "--profile", "pandaset"])
    err = capsys.readouterr().err
    assert code == 1 and "the pandaset profile has no such archive" in err
    assert not (tmp_path / "s.zip").exists()


def test_simulate_writes_a_profiles_layout_and_refuses_a_contradicting_sensor(tmp_path, capsys):
    base = ["simulate", "-q", "--out", str(tmp_path / "d"), "--sequences", "2:1", "5:1"]
    assert (
        main([*base, "--unlabelled", "5", "--azimuth-steps", "128", "--profile", "pandaset"]) == 0
    )
    assert (tmp_path / "d" / "002" / "labels").is_dir() and not (
        tmp_path / "d" / "005" / "labels"
    ).exists()
    scan = next((tmp_path / "d" / "005" / "velodyne").glob("*.bin"))
    assert scan.stat().st_size % 20 == 0
    assert main([*base, "--beams", "32", "--profile", "semantic-poss"]) == 1
    assert "contradicts the semantic-poss profile's 40 rows" in capsys.readouterr().err


def test_profile_show_quotes_every_numeric_split_id_alike(capsys):
    """`08` and `09` are quoted as `'07'` is (YAML would leave them bare), and read back the same."""
    assert main(["profile", "show", "semantickitti"]) == 0
    shown = capsys.readouterr().out
    splits = shown[shown.index("\nsplits:") :]
    items = [line.strip()[2:] for line in splits.splitlines() if line.strip().startswith("- ")]
    ids = [i for i in items if i.strip("'").isdigit()]
    assert len(ids) >= 22 and all(i.startswith("'") and i.endswith("'") for i in ids), ids
    assert yaml.safe_load(shown)["splits"]["valid"] == ["08"]
