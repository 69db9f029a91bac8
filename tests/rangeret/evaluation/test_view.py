"""`rangeret view`: the PLY of the real scan reads back with its points and palette colours, the
PNG has a panel per label file and an error map, and bad label files are refused in one line."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from PIL import Image

from rangeret.cli.main import main
from rangeret.dataset.profiles import load_profile
from rangeret.evaluation.view import IGNORED_RGB, RIGHT_RGB, WRONG_RGB
from rangeret.io.ply import PlyFormatError, read_ply
from rangeret.io.scans import read_labels, read_scan, write_labels, write_scan
from tests.support.paths import data_path


@pytest.fixture(scope="module")
def official_rgb() -> dict[int, tuple[int, int, int]]:
    """The official YAML's color_map (BGR), as RGB by raw id."""
    config = yaml.safe_load(data_path("semantic-kitti.yaml").read_text())
    return {int(raw): tuple(bgr[::-1]) for raw, bgr in config["color_map"].items()}


def _colours(path) -> np.ndarray:
    """The distinct RGB colours of a PNG, as (K, 3)."""
    rgb = np.asarray(Image.open(path).convert("RGB")).reshape(-1, 3)
    return np.unique(rgb, axis=0)


def _has(colours: np.ndarray, rgb: tuple[int, int, int]) -> bool:
    return bool((colours == np.array(rgb)).all(axis=1).any())


def test_ply_of_the_real_scan_holds_its_points_in_the_palette_colours(
    tmp_path, real_scan_path, real_label_path, official_rgb, capsys
):
    out = tmp_path / "scan.ply"
    args = ["view", "-q", str(real_scan_path), "--ground-truth", str(real_label_path)]
    assert main([*args, "--out", str(out)]) == 0
    assert "coloured by the ground truth" in capsys.readouterr().out
    points, truth = read_scan(real_scan_path), read_labels(real_label_path)
    raw = truth & 0xFFFF
    expected_rgb = np.array([official_rgb[int(r)] for r in raw], dtype=np.uint8)

    cloud = read_ply(out)
    assert len(cloud) == len(points) == 123_389
    assert np.array_equal(np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1), points[:, :3])
    assert np.array_equal(
        np.stack([cloud["red"], cloud["green"], cloud["blue"]], axis=1), expected_rgb
    )
    assert np.array_equal(cloud["label"], raw)

    # The same file parsed by hand, as a viewer would.
    data = out.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = [line for line in head.decode("ascii").splitlines() if not line.startswith("comment")]
    assert lines == [
        "ply",
        "format binary_little_endian 1.0",
        f"element vertex {len(points)}",
        "property float x",
        "property float y",
        "property float z",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "property uint label",
    ]
    assert len(body) == len(points) * (3 * 4 + 3 + 4)
    record = np.dtype([("xyz", "<f4", 3), ("rgb", "u1", 3), ("label", "<u4")])
    vertices = np.frombuffer(body, dtype=record)
    assert np.array_equal(vertices["xyz"], points[:, :3])
    assert np.array_equal(vertices["rgb"], expected_rgb)
    assert np.array_equal(vertices["label"], raw)
    # RGB, not the YAML's BGR: car is stored [245, 150, 100] and shows blue.
    assert (vertices["rgb"][raw == 10] == [100, 150, 245]).all()

    png = out.with_suffix(".png")
    assert png.read_bytes()[:4] == b"\x89PNG"
    colours = _colours(png)
    assert len(colours) > 20 and _has(colours, (255, 0, 255)) and _has(colours, (100, 150, 245))


def test_png_with_both_label_files_has_prediction_truth_and_error_panels(
    tmp_path, real_scan_path, real_label_path, capsys
):
    truth = read_labels(real_label_path)
    prediction = truth & 0xFFFF
    road = np.flatnonzero(prediction == 40)
    prediction[road[: len(road) // 2]] = 10  # half the road called car
    write_labels(tmp_path / "pred.label", prediction)
    both, alone = tmp_path / "both.png", tmp_path / "alone.png"
    base = ["view", "-q", str(real_scan_path), "--ground-truth", str(real_label_path)]
    assert main([*base, "--labels", str(tmp_path / "pred.label"), "--out", str(both)]) == 0
    assert main([*base, "--out", str(alone)]) == 0
    assert not (tmp_path / "both.ply").exists()
    capsys.readouterr()

    three, one = Image.open(both), Image.open(alone)
    assert three.height == one.height and three.width > 2 * one.width
    colours = _colours(both)
    for key in (RIGHT_RGB, WRONG_RGB, IGNORED_RGB):
        assert _has(colours, key), key
    assert not _has(_colours(alone), WRONG_RGB)
    # Wrong points show only in the last panel (and the legend beside it).
    rgb = np.asarray(three.convert("RGB"))
    columns = np.flatnonzero((rgb == np.array(WRONG_RGB)).all(axis=2).any(axis=0))
    assert columns.size and columns.min() > 0.6 * three.width


def test_a_label_file_of_another_length_is_refused_in_one_sentence(
    tmp_path, real_scan_path, real_label_path, capsys
):
    short = tmp_path / "short.label"
    write_labels(short, read_labels(real_label_path)[:-5])
    out = tmp_path / "v.ply"
    assert main(["view", str(real_scan_path), "--labels", str(short), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(short) in err
    assert "holds 123384 labels" in err and "has 123389 points" in err
    assert not out.exists() and not out.with_suffix(".png").exists()


def test_a_pandaset_scan_is_read_with_its_five_float_record(tmp_path, capsys):
    profile = load_profile("pandaset")
    rng = np.random.default_rng(0)
    points = rng.normal(0, 10, (500, 5)).astype(np.float32)
    write_scan(tmp_path / "p.bin", points, record=profile.points)
    raw = np.array(profile.labels.class_raw_ids, dtype=np.uint32)[rng.integers(0, 15, 500)]
    write_labels(tmp_path / "p.label", raw)
    args = ["view", "-q", str(tmp_path / "p.bin"), "--labels", str(tmp_path / "p.label")]
    assert main([*args, "--out", str(tmp_path / "p.ply"), "--profile", "pandaset"]) == 0
    cloud = read_ply(tmp_path / "p.ply")
    assert len(cloud) == 500 and np.array_equal(cloud["z"], points[:, 2])
    assert np.array_equal(cloud["label"], raw)
    # Read with SemanticKITTI's 4-float record the same file is 625 points: the labels are refused.
    assert main([*args, "--out", str(tmp_path / "k.ply")]) == 1
    assert "holds 500 labels but the scan" in capsys.readouterr().err


def test_without_labels_the_cloud_is_grey_by_height(tmp_path, real_scan_path, capsys):
    out = tmp_path / "h.ply"
    assert main(["view", "-q", str(real_scan_path), "--out", str(out)]) == 0
    assert "coloured by height" in capsys.readouterr().out
    cloud = read_ply(out)
    assert (cloud["red"] == cloud["green"]).all() and (cloud["green"] == cloud["blue"]).all()
    assert (cloud["label"] == 0).all()
    low, high = np.argmin(cloud["z"]), np.argmax(cloud["z"])
    assert cloud["red"][low] < cloud["red"][high]


def test_an_output_that_is_neither_ply_nor_png_is_refused(tmp_path, real_scan_path, capsys):
    assert main(["view", str(real_scan_path), "--out", str(tmp_path / "v.obj")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "must end with .ply" in err


def test_the_reader_refuses_a_file_that_is_not_a_ply(tmp_path):
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    assert len(read_ply(tmp_path / "a.ply")) == 0
    (tmp_path / "b.ply").write_bytes(b"solid mesh\n")
    with pytest.raises(PlyFormatError, match="is not a PLY file"):
        read_ply(tmp_path / "b.ply")
