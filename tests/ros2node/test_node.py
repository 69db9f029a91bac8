"""`rangeret ros2` end to end, in a loopback-only network namespace: one node (reliable input,
--rgb) answers the real scan as `rangeret predict` labels it, reads other datatypes and layouts
alike, counts and skips bad messages, and stops on SIGTERM with exit 0."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.profiles import load_profile
from rangeret.evaluation.view import label_colours
from rangeret.io.pointcloud2 import FLOAT32, FLOAT64, UINT16, UINT32, decode
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan
from tests.support.ros import Cloud, domain_id_for, drive_node, make_cloud
from tests.support.workers import small_weights

NAMES = ("x", "y", "z", "intensity")
REAL, SUBSAMPLE = 0, 1
VARIANTS = {
    2: "float64 xyz, uint16 intensity",
    3: "padding and a wider point step",
    4: "two rows with row padding",
    5: "big-endian",
}
BAD = {6: "fields", 7: "point_step", 8: "size", 9: "size"}
AFTER_BAD = 10


def columns(points, **datatypes):
    return {n: (datatypes.get(n, FLOAT32), points[:, i]) for i, n in enumerate(NAMES)}


def build_clouds(real_points) -> list[Cloud]:
    """The clouds the driver publishes, by index (see the constants above)."""
    sub = real_points[::5].copy()
    sub[:, 3] = np.round(sub[:, 3] * 100)  # whole hundredths: exact as uint16
    sub = sub[: len(sub) // 2 * 2]
    xyz64 = {n: (FLOAT64, sub[:, i].astype(np.float64)) for i, n in enumerate(NAMES[:3])}
    truncated = make_cloud(columns(sub), expect="bad")
    truncated.data = truncated.data[:-16]
    wrong_step = make_cloud(columns(sub), expect="bad")
    wrong_step.point_step, wrong_step.row_step = 8, 8 * wrong_step.width
    clouds = [
        make_cloud(columns(real_points), frame_id="velodyne", stamp=(1700000000, 123456789)),
        make_cloud(columns(sub)),
        make_cloud({**xyz64, "intensity": (UINT16, sub[:, 3].astype(np.uint16))}),
        make_cloud(columns(sub), gaps=3, point_step=40),
        make_cloud(columns(sub), height=2, row_padding=12),
        make_cloud(columns(sub), bigendian=True),
        make_cloud({n: (FLOAT32, sub[:, i]) for i, n in enumerate(NAMES[:2])}, expect="bad"),
        wrong_step,
        truncated,
        make_cloud(columns(sub), height=2, expect="bad"),
        make_cloud(columns(sub)),
    ]
    clouds[9].height = 3  # 3 rows of width N/2: more points than the data holds
    for i, cloud in enumerate(clouds[1:], start=1):
        cloud.stamp = (i, 0)
    return clouds


@pytest.fixture(scope="module")
def real_points(real_scan_path):
    return read_scan(real_scan_path, KITTI_RECORD)


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    return small_weights(tmp_path_factory.mktemp("weights"))


@pytest.fixture(scope="module")
def drive(tmp_path_factory, weights, real_points):
    args = ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu",
            "--report-every", "0.3", "--input-qos", "reliable", "--rgb"]  # fmt: skip
    clouds = build_clouds(real_points)
    result = drive_node(tmp_path_factory.mktemp("node"), args, clouds, domain_id=domain_id_for(1))
    return clouds, result


@pytest.fixture(scope="module")
def predicted(tmp_path_factory, weights, real_scan_path):
    """`rangeret predict --dataset`'s labels of the real scan with the same weights."""
    root = tmp_path_factory.mktemp("dataset")
    scan = root / "sequences" / "08" / "velodyne" / "000000.bin"
    scan.parent.mkdir(parents=True)
    scan.write_bytes(real_scan_path.read_bytes())
    out = root.parent / "pred"
    code = rangeret_main(
        ["predict", "--dataset", str(root), "--sequences", "08", "--out", str(out),
         "--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu", "-q"]
    )  # fmt: skip
    assert code == 0
    return read_labels(out / "sequences" / "08" / "predictions" / "000000.label")


def fields_of(cloud: Cloud) -> dict[str, np.ndarray]:
    return decode(cloud, "answer")[1]


def test_the_real_scan_comes_back_with_its_fields_header_and_label_confidence_rgb(drive):
    clouds, result = drive
    sent, answer = clouds[REAL], result.answers[REAL]
    assert (answer.frame_id, answer.stamp) == ("velodyne", (1700000000, 123456789))
    assert (answer.height, answer.width) == (1, 123389)
    assert [(f.name, f.offset, f.datatype) for f in answer.fields] == [
        *((f.name, f.offset, f.datatype) for f in sent.fields),
        ("label", 16, UINT32),
        ("confidence", 20, FLOAT32),
        ("rgb", 24, FLOAT32),
    ]
    assert (answer.point_step, answer.row_step) == (28, 28 * 123389)
    got, expected = fields_of(answer), fields_of(sent)
    for name in NAMES:
        np.testing.assert_array_equal(got[name], expected[name])
    assert np.all((got["confidence"] >= 0) & (got["confidence"] <= 1))


def test_the_real_scan_is_labelled_as_rangeret_predict_labels_it(drive, predicted):
    _, result = drive
    labels = fields_of(result.answers[REAL])["label"]
    assert labels.dtype == np.uint32
    assert labels.tobytes() == predicted.astype(np.uint32).tobytes()
    assert len(np.unique(labels)) > 1


def test_other_datatypes_padding_and_rows_give_the_float32_labels(drive):
    _, result = drive
    reference = fields_of(result.answers[SUBSAMPLE])
    for index, name in VARIANTS.items():
        got = fields_of(result.answers[index])
        np.testing.assert_array_equal(got["label"], reference["label"], err_msg=name)
        np.testing.assert_array_equal(got["confidence"], reference["confidence"], err_msg=name)


def test_the_rgb_field_is_the_palette_colour_of_each_label(drive):
    _, result = drive
    got = fields_of(result.answers[REAL])
    packed = got["rgb"].view(np.uint32)
    rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1)
    expected = label_colours(got["label"], load_profile("semantickitti").labels)
    np.testing.assert_array_equal(rgb, expected)


def test_bad_messages_are_counted_logged_once_per_kind_and_skipped(drive):
    _, result = drive
    values = result.diagnostics
    assert values["bad"] == "4"
    assert (values["bad_fields"], values["bad_point_step"], values["bad_size"]) == ("1", "1", "2")
    assert set(result.answers) == {REAL, SUBSAMPLE, *VARIANTS, AFTER_BAD}  # still running
    assert int(values["labelled"]) >= len(result.answers)
    warnings = [line for line in result.log.splitlines() if "skipped a message" in line]
    assert len(warnings) == 3, warnings
    assert any("/points: has no z field" in w for w in warnings)
    assert any("does not fit in point_step 8" in w for w in warnings)
    assert any("holds" in w and "bytes of data" in w for w in warnings)


def test_the_diagnostics_report_latency_counts_and_the_run(drive, weights):
    _, result = drive
    values, status = result.diagnostics, result.status
    assert status["name"] == "rangeret: labelling"
    for key in ("dropped", "interval_s", "latency_p50_ms", "latency_p95_ms", "overhead_p50_ms"):
        assert key in values
    assert values["input_topic"] == "/points" and values["output_topic"] == "/points_labelled"
    assert values["checkpoint_sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()[:12]
    assert (values["profile"], values["device"], values["knn"]) == ("semantickitti", "cpu", "on")


def test_the_startup_line_names_weights_profile_device_topics_and_qos(drive, weights):
    _, result = drive
    (line,) = [line for line in result.log.splitlines() if "labelling /points" in line]
    sha = hashlib.sha256(weights.read_bytes()).hexdigest()[:12]
    for part in (f"from {weights} (sha256 {sha})", "semantickitti profile", "32x256 on cpu",
                 "/points (reliable, keep last 5)", "/points_labelled (reliable, keep last 1",
                 "with rgb", "kNN on"):  # fmt: skip
        assert part in line, part


def test_sigterm_stops_the_node_cleanly(drive):
    _, result = drive
    assert result.returncode == 0, result.log[-3000:]
    assert "Traceback" not in result.log
    assert "stopped: the node is destroyed and ROS 2 shut down" in result.log
