"""`rangeret ros2 --panoptic` end to end, in a loopback-only network namespace: the node (with
--rgb and its own clustering options) answers the real scan, and the scan with missing returns,
with an `instance` field holding the objects `rangeret predict --dataset --panoptic` finds with
the same options, `label` the raw ids; the run names its clustering in its startup line and on
/diagnostics; a profile without thing classes is refused in one sentence."""

from __future__ import annotations

import numpy as np
import pytest

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.layout import KITTI_LAYOUT, prediction_path, velodyne_dir
from rangeret.dataset.profiles import load_profile
from rangeret.evaluation.view import label_colours
from rangeret.io.pointcloud2 import FLOAT32, UINT32, decode
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan
from tests.rangeret.cli.test_panoptic_files_and_bags import panoptic_checkpoint, with_holes
from tests.support.ros import Cloud, domain_id_for, drive_node, make_cloud

NAMES = ("x", "y", "z", "intensity")
#: Clustering options other than the defaults, which the node must pass on.
CLUSTERING = ["--cluster-angle", "15", "--min-cluster-points", "5"]
NET = ["--device", "cpu", "--panoptic", *CLUSTERING]
REAL, HOLES = 0, 1


def cloud_of(points: np.ndarray, second: int) -> Cloud:
    columns = {n: (FLOAT32, points[:, i]) for i, n in enumerate(NAMES)}
    return make_cloud(columns, stamp=(second, 0))


@pytest.fixture(scope="module")
def real_points(real_scan_path):
    return read_scan(real_scan_path, KITTI_RECORD)


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    return panoptic_checkpoint(tmp_path_factory.mktemp("weights") / "kitti32.pt")


@pytest.fixture(scope="module")
def drive(tmp_path_factory, weights, real_points):
    args = ["--checkpoint", str(weights), *NET, "--report-every", "0.3", "--input-qos",
            "reliable", "--rgb"]  # fmt: skip
    clouds = [cloud_of(real_points, 1), cloud_of(with_holes(real_points)[0], 2)]
    result = drive_node(tmp_path_factory.mktemp("node"), args, clouds, domain_id=domain_id_for(3))
    return clouds, result


@pytest.fixture(scope="module")
def predicted(tmp_path_factory, weights, real_scan_path):
    """`rangeret predict --dataset --panoptic`'s labels of the real scan, same options."""
    root = tmp_path_factory.mktemp("dataset")
    scan = velodyne_dir(root, "08", layout=KITTI_LAYOUT) / "000000.bin"
    scan.parent.mkdir(parents=True)
    scan.write_bytes(real_scan_path.read_bytes())
    out = tmp_path_factory.mktemp("pred")
    args = ["predict", "-q", "--dataset", str(root), "--sequences", "08", "--out", str(out)]
    assert rangeret_main([*args, "--checkpoint", str(weights), *NET]) == 0
    labels = read_labels(prediction_path(out, "08", "000000"))
    assert len(np.unique(labels >> 16)) > 20
    return labels


def fields_of(cloud: Cloud) -> dict[str, np.ndarray]:
    return decode(cloud, "answer")[1]


def test_the_answer_adds_instance_after_label_and_confidence(drive):
    clouds, result = drive
    answer = result.answers[REAL]
    assert [(f.name, f.offset, f.datatype) for f in answer.fields[4:]] == [
        ("label", 16, UINT32),
        ("confidence", 20, FLOAT32),
        ("instance", 24, UINT32),
        ("rgb", 28, FLOAT32),
    ]
    assert answer.point_step == 32
    got, sent = fields_of(answer), fields_of(clouds[REAL])
    for name in NAMES:
        np.testing.assert_array_equal(got[name], sent[name])


def test_the_real_scan_gets_the_objects_of_rangeret_predict(drive, predicted):
    _, result = drive
    got = fields_of(result.answers[REAL])
    assert got["instance"].tobytes() == (predicted >> 16).tobytes()
    assert got["label"].tobytes() == (predicted & 0xFFFF).tobytes()
    packed = got["rgb"].view(np.uint32)
    rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1)
    np.testing.assert_array_equal(
        rgb, label_colours(got["label"], load_profile("semantickitti").labels)
    )


def test_missing_returns_have_no_object_and_the_others_keep_theirs(drive, predicted, real_points):
    _, result = drive
    _, valid = with_holes(real_points)
    got = fields_of(result.answers[HOLES])
    np.testing.assert_array_equal(got["instance"][valid], predicted >> 16)
    assert (got["instance"][~valid] == 0).all() and (got["label"][~valid] == 0).all()


def test_the_run_names_its_clustering(drive):
    _, result = drive
    fact = "on (cluster angle 15 deg, min 5 points)"
    assert result.diagnostics["panoptic"] == fact
    assert result.diagnostics["bad"] == "0"
    (line,) = [line for line in result.log.splitlines() if "labelling /points" in line]
    assert f"kNN on, panoptic {fact}" in line
    assert result.returncode == 0 and "Traceback" not in result.log


def test_a_profile_without_thing_classes_is_refused_in_one_sentence(tmp_path, capsys):
    weights = panoptic_checkpoint(tmp_path / "pandaset32.pt", "pandaset")
    assert rangeret_main(["ros2", "--checkpoint", str(weights), *NET]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert "the pandaset profile names no thing classes, so --panoptic has no objects" in err
