"""`rangeret predict --files` and `--bag` with --panoptic: the real scan's `.label` file holds the
panoptic labels `predict --dataset --panoptic` writes for it, byte for byte (their low 16 bits
the labels of a run without --panoptic); labelled copies and labelled bags keep the raw id in
`label` and add `instance`, the dataset runner's objects for the same points (0 at invalid
points); a profile without thing classes is refused in one line, a semantic folder is not
labelled into as a panoptic one, and a message with more objects than its label holds is
written through while the others are labelled.

The network is a 1-block rangeret-cir with random weights at 32 x 256 whose argmax finds cars,
people and other things in the real scan, saved with the semantickitti profile.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from rangeret.cli.main import main
from rangeret.dataset.layout import KITTI_LAYOUT, prediction_path, velodyne_dir
from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.inference.files_runner import field_labels
from rangeret.inference.results import ScanPrediction
from rangeret.io.panoptic_labels import SHIFTED, THOUSANDS
from rangeret.io.point_files import read_point_file
from rangeret.io.pointcloud2 import FLOAT32, UINT32, decode
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan, write_scan
from rangeret.models import build_model, save_checkpoint
from tests.support.bags import Cloud, read_bag, write_bag
from tests.support.point_files import pcd_bytes, ply_bytes

NET = ["--device", "cpu", "-q"]
#: Every HOLE-th point of the real scan is preceded by a point without coordinates.
HOLE = 97


def small_profile(name: str) -> DatasetProfile:
    """A built-in profile at 32 x 256."""
    profile = load_profile(name)
    projection = dataclasses.replace(profile.projection, height=32, width=256)
    return dataclasses.replace(profile, projection=projection)


def panoptic_checkpoint(path: Path, profile: str = "semantickitti") -> Path:
    """Random weights of a 1-block rangeret-cir whose argmax varies from pixel to pixel, saved
    with `profile` at 32 x 256 (seeded: the same file every time)."""
    small = small_profile(profile)
    net = build_model("rangeret-cir", 32, 256, num_classes=small.num_classes, layers=1).eval()
    g = torch.Generator().manual_seed(2)
    state = {
        k: torch.randn(v.shape, generator=g) * 0.5
        if v.is_floating_point() and not k.endswith("running_var")
        else v
        for k, v in net.state_dict().items()
    }
    net.load_state_dict(state)
    save_checkpoint(path, net, profile=small.to_dict())
    return path


def with_holes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points with a NaN point before every HOLE-th one, and where the real ones lie."""
    at = np.arange(0, len(points), HOLE)
    holes = np.insert(points, at, np.nan, axis=0)
    valid = np.ones(len(holes), dtype=bool)
    valid[at + np.arange(len(at))] = False
    return holes, valid


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("panoptic-sources")


@pytest.fixture(scope="module")
def checkpoint(base: Path) -> Path:
    return panoptic_checkpoint(base / "kitti32.pt")


@pytest.fixture(scope="module")
def points(real_scan_path: Path) -> np.ndarray:
    return read_scan(real_scan_path)


@pytest.fixture(scope="module")
def reference(base: Path, checkpoint: Path, real_scan_path: Path) -> np.ndarray:
    """`rangeret predict --dataset --panoptic`'s labels of the real scan."""
    scan = velodyne_dir(base / "data", "08", layout=KITTI_LAYOUT) / "000000.bin"
    scan.parent.mkdir(parents=True)
    scan.write_bytes(real_scan_path.read_bytes())
    args = ["predict", "--dataset", str(base / "data"), "--sequences", "08"]
    args += ["--out", str(base / "tree"), "--checkpoint", str(checkpoint), "--panoptic", *NET]
    assert main(args) == 0
    labels = read_labels(prediction_path(base / "tree", "08", "000000"))
    assert len(np.unique(labels >> 16)) > 20  # the network finds objects
    assert ((labels >> 16) == 0).mean() > 0.5  # and stuff
    return labels


@pytest.fixture(scope="module")
def files(base: Path, checkpoint: Path, points: np.ndarray) -> Path:
    """The real scan as `.bin`, binary PLY and, with missing returns, binary PCD, labelled by
    one `predict --files --panoptic --write-labelled` run."""
    inputs = base / "in"
    inputs.mkdir()
    write_scan(inputs / "scan.bin", points, record=KITTI_RECORD)
    (inputs / "scan-ply.ply").write_bytes(ply_bytes(points, "binary_little_endian"))
    (inputs / "holes.pcd").write_bytes(pcd_bytes(with_holes(points)[0], "binary"))
    out = base / "files"
    args = ["predict", "--files", str(inputs), "--out", str(out), "--checkpoint", str(checkpoint)]
    assert main([*args, "--panoptic", "--write-labelled", "--save-confidence", *NET]) == 0
    return out


@pytest.fixture(scope="module")
def semantic(base: Path, checkpoint: Path) -> Path:
    """The `.bin` scan labelled by `predict --files` without --panoptic."""
    out = base / "semantic"
    args = ["predict", "--files", str(base / "in" / "scan.bin"), "--out", str(out)]
    assert main([*args, "--checkpoint", str(checkpoint), *NET]) == 0
    return out


def test_a_bin_scan_gets_the_panoptic_labels_of_predict_dataset(files, reference, semantic):
    got = read_labels(files / "scan.label")
    assert got.tobytes() == reference.tobytes()
    assert (got & 0xFFFF).tobytes() == read_labels(semantic / "scan.label").tobytes()
    assert np.array_equal(read_labels(files / "scan-ply.label"), reference)


def test_labelled_copies_hold_raw_ids_and_the_dataset_runners_instances(files, reference):
    ply = read_point_file(files / "scan-ply.labelled.ply", record=KITTI_RECORD)
    assert list(ply.columns)[-3:] == ["label", "confidence", "instance"]
    assert ply.columns["instance"].dtype == np.uint32
    assert np.array_equal(ply.columns["instance"], reference >> 16)
    assert np.array_equal(ply.columns["label"], reference & 0xFFFF)
    assert not list(files.glob("scan.labelled*"))  # a .bin's labelled form is its .label


def test_points_without_coordinates_have_no_object_and_the_others_keep_theirs(
    files, reference, points
):
    _, valid = with_holes(points)
    pcd = read_point_file(files / "holes.labelled.pcd", record=KITTI_RECORD)
    instance, label = pcd.columns["instance"], pcd.columns["label"]
    assert np.array_equal(instance[valid], reference >> 16)
    assert np.array_equal(label[valid], reference & 0xFFFF)
    assert (instance[~valid] == 0).all() and (label[~valid] == 0).all()
    assert np.array_equal(read_labels(files / "holes.label")[valid], reference)


def test_run_json_records_panoptic_and_each_files_objects(files, reference):
    record = json.loads((files / "run.json").read_text())
    assert record["panoptic"] == {"angle": 10.0, "min_points": 10}
    assert record["runs"][-1]["panoptic"] == record["panoptic"]
    objects = len(np.unique(reference >> 16)) - 1
    by_stem = {Path(i["file"]).stem: i for i in record["inputs"]}
    assert {k: v["instances"] for k, v in by_stem.items()} == dict.fromkeys(by_stem, objects)


def test_a_folder_of_semantic_labels_is_refused_before_any_file_is_labelled(
    semantic, checkpoint, base, capsys
):
    before = (semantic / "scan.label").read_bytes()
    args = ["predict", "--files", str(base / "in" / "scan.bin"), "--out", str(semantic)]
    capsys.readouterr()
    assert main([*args, "--checkpoint", str(checkpoint), "--panoptic", *NET]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds semantic predictions and this run is panoptic" in err
    assert (semantic / "scan.label").read_bytes() == before


def _cloud(points: np.ndarray, stamp: tuple[int, int] = (1_600_000_000, 5)) -> Cloud:
    names = ("x", "y", "z", "intensity")
    return Cloud([(n, FLOAT32, points[:, i]) for i, n in enumerate(names)], stamp=stamp)


def test_a_labelled_bag_gets_an_instance_field_of_the_dataset_runners_objects(
    base, checkpoint, points, reference
):
    holes, valid = with_holes(points)
    source = write_bag(base / "drive", "rosbag2-mcap", [_cloud(points), _cloud(holes)])
    out = base / "drive-labelled.bag"
    args = ["predict", "--bag", str(source), "--topic", "/points", "--out", str(out)]
    args += ["--bag-format", "ros1", "--checkpoint", str(checkpoint), "--panoptic", *NET]
    assert main(args) == 0
    whole, holed = [m[4] for m in read_bag(out) if m[0] == "/points"]
    assert [(f.name, f.offset, f.datatype) for f in whole.fields[4:]] == [
        ("label", 16, UINT32),
        ("confidence", 20, FLOAT32),
        ("instance", 24, UINT32),
    ]
    columns = decode(whole, "whole")[1]
    assert np.array_equal(columns["instance"], reference >> 16)
    assert np.array_equal(columns["label"], reference & 0xFFFF)
    columns = decode(holed, "holes")[1]
    assert np.array_equal(columns["instance"][valid], reference >> 16)
    assert (columns["instance"][~valid] == 0).all() and (columns["label"][~valid] == 0).all()
    record = json.loads((base / "drive-labelled.bag.run.json").read_text())
    assert record["panoptic"] == {"angle": 10.0, "min_points": 10}
    assert record["instances"] == 2 * (len(np.unique(reference >> 16)) - 1)


def test_a_message_with_more_objects_than_its_label_holds_is_written_through(
    base, checkpoint, points, monkeypatch, capsys
):
    """With a label that holds one object, the real scan's message fails on its own (kind
    `input`, written unchanged) and a cloud without valid points is still labelled."""
    monkeypatch.setattr(
        "rangeret.dataset.layout.SHIFTED", dataclasses.replace(SHIFTED, max_instance=1)
    )
    empty = np.full((8, 4), np.nan, dtype=np.float32)
    source = write_bag(base / "crowd", "rosbag2-sqlite3", [_cloud(points), _cloud(empty)])
    out = base / "crowd-labelled"
    args = ["predict", "--bag", str(source), "--topic", "/points", "--out", str(out)]
    capsys.readouterr()
    assert main([*args, "--checkpoint", str(checkpoint), "--panoptic", *NET]) == 1
    err = capsys.readouterr().err
    assert "1 of 2 /points messages could not be labelled" in err and "Traceback" not in err
    sent = [m[3] for m in read_bag(source) if m[0] == "/points"]
    crowd, nothing = [m for m in read_bag(out) if m[0] == "/points"]
    assert crowd[3] == sent[0]
    columns = decode(nothing[4], "empty")[1]
    assert (columns["instance"] == 0).all() and (columns["label"] == 0).all()
    record = json.loads((base / "crowd-labelled.run.json").read_text())
    (failed,) = record["failed"]
    assert failed["index"] == 0 and failed["kind"] == "input"
    assert "a SemanticKITTI panoptic label holds at most 1" in failed["reason"]


@pytest.mark.parametrize("source", ["files", "bag"])
def test_a_profile_without_thing_classes_is_refused_in_one_sentence(base, points, source, capsys):
    weights = base / "pandaset32.pt"
    if not weights.exists():
        panoptic_checkpoint(weights, "pandaset")
    out = base / f"pandaset-{source}"
    if source == "files":
        (base / "pandaset.pcd").write_bytes(pcd_bytes(points[:100], "binary"))
        args = ["predict", "--files", str(base / "pandaset.pcd"), "--out", str(out)]
    else:
        bag = write_bag(base / "pandaset-in", "rosbag2-sqlite3", [_cloud(points[:100])])
        args = ["predict", "--bag", str(bag), "--topic", "/points", "--out", str(out)]
    capsys.readouterr()
    assert main([*args, "--checkpoint", str(weights), "--panoptic", *NET]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert "the pandaset profile names no thing classes, so --panoptic has no objects" in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("profile", "encoding"), [("semantickitti", SHIFTED), ("nuscenes", THOUSANDS)]
)
def test_a_label_field_holds_what_a_run_without_panoptic_writes(profile, encoding):
    """SemanticKITTI's raw ids and nuScenes' classes, never the packed panoptic value (for
    nuScenes `1000 x class + instance`)."""
    semantic = np.array([0, 4, 4, 17, 4, 11], dtype=np.uint32)
    instances = np.array([0, 3, 3, 0, 9, 0], dtype=np.uint32)
    predictor = SimpleNamespace(profile=load_profile(profile))
    plain = ScanPrediction(semantic)
    assert field_labels(predictor, plain) is semantic
    found = ScanPrediction(encoding.encode(semantic, instances, semantic), instances=instances)
    assert not np.array_equal(found.labels, semantic)
    assert np.array_equal(field_labels(predictor, found), semantic)
