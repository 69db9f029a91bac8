"""A PointCloud2 of any datatype and layout as the record, and the answer built from it (with
panoptic segmentation's `instance` field; colours by what the `label` field holds)."""

from __future__ import annotations

import numpy as np
import pytest

from rangeret.dataset.profiles import load_profile
from rangeret.evaluation.view import label_colours
from rangeret.exceptions import InputError
from rangeret.inference.results import ScanPrediction
from rangeret.io.point_fields import PointFieldsError
from rangeret.io.pointcloud2 import FLOAT32, FLOAT64, UINT16, UINT32, CloudMessageError, decode
from rangeret.io.scans import KITTI_RECORD, read_scan
from ros2node.clouds import FieldMapping, cloud_record, labelled_message, palette_of
from ros2node.node import problem_kind, skip_kind
from tests.support.ros import make_cloud
from tests.support.ros_driver import to_message

PROFILE = load_profile("semantickitti")
MAPPING = FieldMapping(PROFILE.points, PROFILE.reflectance_fill, {})
NAMES = ("x", "y", "z", "intensity")


@pytest.fixture(scope="module")
def points(real_scan_path):
    """Every 50th point of the real scan, the reflectance in whole hundredths (exact as uint16)."""
    pts = read_scan(real_scan_path, KITTI_RECORD)[::50].copy()
    pts[:, 3] = np.round(pts[:, 3] * 100)
    return pts[: len(pts) // 2 * 2]


def float32_cloud(points):
    return make_cloud({n: (FLOAT32, points[:, i]) for i, n in enumerate(NAMES)}, stamp=(3, 4))


def with_point_step(cloud, step):
    """The cloud claiming another point step (its fields and data unchanged)."""
    cloud.point_step, cloud.row_step = step, step * cloud.width
    return cloud


def variants(points):
    xyz64 = {n: (FLOAT64, points[:, i].astype(np.float64)) for i, n in enumerate(NAMES[:3])}
    return {
        "float64 xyz, uint16 intensity": make_cloud(
            {**xyz64, "intensity": (UINT16, points[:, 3].astype(np.uint16))}
        ),
        "padding and a wider point step": make_cloud(
            {n: (FLOAT32, points[:, i]) for i, n in enumerate(NAMES)}, gaps=3, point_step=40
        ),
        "two rows with row padding": make_cloud(
            {n: (FLOAT32, points[:, i]) for i, n in enumerate(NAMES)}, height=2, row_padding=12
        ),
        "big-endian": make_cloud(
            {n: (FLOAT32, points[:, i]) for i, n in enumerate(NAMES)}, bigendian=True
        ),
    }


def test_every_layout_gives_the_float32_record(points):
    _, reference = cloud_record(to_message(float32_cloud(points)), "ref", MAPPING)
    np.testing.assert_array_equal(reference.points, points)
    for name, cloud in variants(points).items():
        layout, record = cloud_record(to_message(cloud), name, MAPPING)
        assert layout.num_points == len(points), name
        np.testing.assert_array_equal(record.points, reference.points, err_msg=name)
        assert record.sources["remission"] == "intensity"


def test_the_answer_keeps_the_input_and_adds_label_and_confidence(points):
    cloud = variants(points)["padding and a wider point step"]
    msg = to_message(cloud)
    layout, _ = cloud_record(msg, "padded", MAPPING)
    labels = ScanPrediction(
        np.arange(len(points), dtype=np.uint32) % 260,
        np.linspace(0, 1, len(points), dtype=np.float32),
    )
    answer = labelled_message(msg, layout, labels)
    assert answer.header == msg.header
    assert [(f.name, f.offset, f.datatype) for f in answer.fields] == [
        *((f.name, f.offset, f.datatype) for f in cloud.fields),
        ("label", 40, UINT32),
        ("confidence", 44, FLOAT32),
    ]
    assert (answer.point_step, answer.row_step) == (48, 48 * len(points))
    _, got = decode(answer, "answer")
    _, sent = decode(msg, "sent")
    for name in NAMES:
        np.testing.assert_array_equal(got[name], sent[name])
    np.testing.assert_array_equal(got["label"], labels.labels)
    np.testing.assert_array_equal(got["confidence"], labels.confidence)
    assert "rgb" not in got


def test_the_rgb_field_is_the_palette_colour_of_each_label(points):
    msg = to_message(float32_cloud(points))
    layout, _ = cloud_record(msg, "cloud", MAPPING)
    raw = np.array([0, 10, 40, 44, 48, 70, 252], dtype=np.uint32)
    labels = ScanPrediction(np.resize(raw, len(points)), np.zeros(len(points), np.float32))
    answer = labelled_message(msg, layout, labels, palette_of(PROFILE))
    _, got = decode(answer, "answer")
    packed = got["rgb"].view(np.uint32)
    rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1)
    np.testing.assert_array_equal(rgb, label_colours(labels.labels, PROFILE.labels))
    assert len({tuple(c) for c in rgb[: len(raw)]}) > 3  # the classes have their own colours


@pytest.mark.parametrize(
    ("cloud", "error", "kind"),
    [
        (lambda p: make_cloud({n: (FLOAT32, p[:, i]) for i, n in enumerate(NAMES[:2])}),
         PointFieldsError, "fields"),
        (lambda p: with_point_step(float32_cloud(p), 8), CloudMessageError, "point_step"),
    ],
    ids=["missing z", "fields past the point step"],
)  # fmt: skip
def test_a_bad_message_names_its_source_and_kind(points, cloud, error, kind):
    with pytest.raises(error, match=r"^/points: ") as raised:
        cloud_record(to_message(cloud(points)), "/points", MAPPING)
    assert problem_kind(raised.value) == kind


def test_the_answer_takes_an_instance_field_after_confidence_and_before_rgb(points):
    msg = to_message(float32_cloud(points))
    layout, _ = cloud_record(msg, "cloud", MAPPING)
    n = len(points)
    labels = ScanPrediction(
        np.resize(np.array([10, 40, 30], np.uint32), n),
        np.full(n, 0.5, np.float32),
        instances=np.resize(np.array([1, 0, 2], np.uint32), n),
    )
    answer = labelled_message(msg, layout, labels, palette_of(PROFILE))
    assert [(f.name, f.offset, f.datatype) for f in answer.fields[4:]] == [
        ("label", 16, UINT32),
        ("confidence", 20, FLOAT32),
        ("instance", 24, UINT32),
        ("rgb", 28, FLOAT32),
    ]
    _, got = decode(answer, "answer")
    np.testing.assert_array_equal(got["instance"], labels.instances)
    np.testing.assert_array_equal(got["label"], labels.labels)


def test_nuscenes_labels_are_classes_and_take_their_class_colour():
    """nuScenes labels are training classes, not raw ids: a car (class 4) is the car's orange,
    not the colour of raw id 4 (a pedestrian's)."""
    nuscenes = load_profile("nuscenes")
    config = nuscenes.labels
    classes = np.arange(config.num_classes, dtype=np.uint32)
    packed = palette_of(nuscenes)[classes].view(np.uint32)
    rgb = np.stack([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255], axis=1)
    np.testing.assert_array_equal(rgb, config.class_rgb()[classes])
    assert rgb[config.class_names.index("car")].tolist() == [255, 158, 0]


def test_a_message_the_network_fails_on_is_counted_as_network_and_bad_input_as_its_kind():
    assert skip_kind(RuntimeError("CUDA out of memory")) == "network"
    assert skip_kind(InputError("the scan has 1000 objects of class 4")) == "input"
    assert skip_kind(PointFieldsError("/points: has no z field")) == "fields"
