"""Labelling a bag: each cloud's labels are those `label_cloud` gives for the same points, every
input field, point and other message is kept, and a bad message is written through and named."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import pytest

from rangeret.inference import bag_runner
from rangeret.inference.bag_runner import label_bag
from rangeret.inference.clouds import label_cloud, unlabelled_raw_id
from rangeret.inference.predictor import Predictor
from rangeret.inference.spec import InferenceSpec
from rangeret.io.bags import BagError
from rangeret.io.point_fields import to_record
from rangeret.io.pointcloud2 import FLOAT32, FLOAT64, UINT16, UINT32, decode
from rangeret.io.scans import read_scan
from rangeret.sim.raycast import SensorConfig, simulate_scan
from rangeret.sim.street import make_scene
from tests.support.bags import FORMATS, Cloud, pointcloud2, read_bag, write_bag
from tests.support.workers import small_weights


@pytest.fixture(scope="module")
def predictor(tmp_path_factory):
    weights = small_weights(tmp_path_factory.mktemp("weights"))
    spec = InferenceSpec(checkpoint=str(weights), height=32, width=256, device="cpu")
    return Predictor.from_spec(spec)


@pytest.fixture(scope="module")
def points(real_scan_path) -> np.ndarray:
    return read_scan(real_scan_path)


def _dense(pts: np.ndarray, reflectance: str = "intensity") -> Cloud:
    names = ["x", "y", "z", reflectance]
    return Cloud([(n, FLOAT32, pts[:, i]) for i, n in enumerate(names)])


def _odd(pts: np.ndarray) -> Cloud:
    """An organised (2-row) big-endian cloud with float64 positions, padding in each point and
    row, a ring field, an old `label` field and NaN returns."""
    pts = pts[: len(pts) // 2 * 2].astype(np.float64)
    pts[::97, 0] = np.nan
    n = len(pts)
    fields = [
        ("intensity", FLOAT32, pts[:, 3]),
        ("x", FLOAT64, pts[:, 0]),
        ("y", FLOAT64, pts[:, 1]),
        ("z", FLOAT64, pts[:, 2]),
        ("ring", UINT16, np.arange(n) % 64),
        ("label", UINT32, np.full(n, 99)),
    ]
    return Cloud(fields, offsets=[0, 8, 16, 24, 34, 36], point_step=48, row_pad=6, height=2,
                 bigendian=True, stamp=(1_700_000_000, 123), frame="lidar_top")  # fmt: skip


def _simulated(pose_x: float) -> np.ndarray:
    """A small simulated scan of a street (32 beams x 512 columns)."""
    scene = make_scene(np.random.default_rng(3))
    sensor = SensorConfig(beams=32, azimuth_steps=512)
    points, _ = simulate_scan(scene, pose_x, sensor, np.random.default_rng(4))
    return points


def _clouds(points: np.ndarray) -> list[Cloud]:
    """The real scan, a subsampled and an odd-layout copy of it, and a simulated scan."""
    return [_dense(points), _dense(points[1::9]), _odd(points[::5]), _dense(_simulated(80.0))]


def _expected(predictor, cloud: Cloud) -> tuple[np.ndarray, np.ndarray]:
    columns = {name: np.asarray(v) for name, _, v in cloud.fields}
    profile = predictor.profile
    record = to_record(columns, record=profile.points, source="expected",
                       reflectance_fill=profile.reflectance_fill)  # fmt: skip
    labels = label_cloud(predictor, record)
    return labels.labels, labels.confidence


def _name(fmt: str, stem: str) -> str:
    return stem + (".bag" if fmt == "ros1" else "")


@pytest.mark.parametrize(
    ("fmt_in", "fmt_out"),
    [(f, f) for f in FORMATS] + [("ros1", "rosbag2-mcap"), ("rosbag2-sqlite3", "ros1")],
)
def test_each_cloud_gets_the_labels_of_its_points_and_the_rest_is_kept(
    tmp_path, predictor, points, fmt_in, fmt_out
):
    clouds = _clouds(points)
    source = write_bag(tmp_path / _name(fmt_in, "in"), fmt_in, clouds)
    target = tmp_path / _name(fmt_out, "out")
    summary = label_bag(predictor, source, "/points", target,
                        target_format=fmt_out, progress=False)  # fmt: skip
    assert summary.ok and summary.labelled == summary.messages == 4
    assert summary.other_messages == 9
    before, after = read_bag(source), read_bag(target)
    assert [m[:3] for m in after] == [m[:3] for m in before]  # topics, types, timestamps
    k = 0
    for (topic, _, _, raw_in, msg_in), (_, _, _, raw_out, msg_out) in zip(before, after, strict=True):  # fmt: skip
        if topic != "/points":
            if fmt_in == fmt_out:
                assert raw_out == raw_in
            continue
        cloud = clouds[k]
        k += 1
        names = [f[0] for f in cloud.fields]
        kept = [n for n in names if n != "label"]
        assert [f.name for f in msg_out.fields] == [*kept, "label", "confidence"]
        assert (msg_out.header.stamp.sec, msg_out.header.stamp.nanosec) == cloud.stamp
        assert msg_out.header.frame_id == cloud.frame
        assert (msg_out.height, msg_out.width, msg_out.is_bigendian) == (
            msg_in.height, msg_in.width, msg_in.is_bigendian,
        )  # fmt: skip
        _, columns_in = decode(msg_in, "in")
        _, columns = decode(msg_out, "out")
        for name in kept:
            np.testing.assert_array_equal(columns[name], columns_in[name])
        labels, confidence = _expected(predictor, cloud)
        np.testing.assert_array_equal(columns["label"], labels)
        np.testing.assert_array_equal(columns["confidence"], confidence)
        assert columns["label"].dtype == np.uint32 and columns["confidence"].dtype == np.float32
    assert k == 4
    nan = np.isnan(np.asarray(clouds[2].fields[1][2]))
    _, odd = decode([m[4] for m in after if m[0] == "/points"][2], "odd")
    assert nan.any() and np.all(odd["label"][nan] == unlabelled_raw_id(predictor.label_config))
    assert np.all(odd["confidence"][nan] == 0)

    record = json.loads((tmp_path / (target.name + ".run.json")).read_text())
    assert record["input_bag"] == str(source) and record["output_bag"] == str(target)
    assert (record["storage_in"], record["storage_out"], record["topic"]) == (
        fmt_in, fmt_out, "/points",
    )  # fmt: skip
    assert record["messages_labelled"] == 4 and record["messages_failed"] == 0
    assert record["points"] == sum(c.num_points for c in clouds)
    assert record["invalid_points"] == int(nan.sum())
    assert record["field_sources"] == [{"x": "x", "y": "y", "z": "z", "remission": "intensity"}]
    assert record["reflectance_fill"] == predictor.profile.reflectance_fill
    assert record["checkpoint_sha256"] == predictor.describe()["checkpoint_sha256"]
    assert record["runner"] == "rangeret predict --bag"


def _missing_x(store):
    return pointcloud2(store, Cloud([("y", FLOAT32, np.ones(5)), ("z", FLOAT32, np.ones(5))]))


def _truncated(store):
    msg = pointcloud2(store, _dense(np.ones((8, 4), np.float32)))
    return dataclasses.replace(msg, data=msg.data[:-5])


def test_a_bad_message_is_written_through_and_named(tmp_path, predictor, points, caplog):
    clouds = [_dense(points[::20]), _missing_x, _truncated, _dense(points[::30]), _truncated]
    source = write_bag(tmp_path / "in", "rosbag2-mcap", clouds)
    target = tmp_path / "out"
    with caplog.at_level(logging.WARNING, logger=bag_runner.__name__):
        summary = label_bag(predictor, source, "/points", target, progress=False)
    assert not summary.ok and summary.labelled == 2 and summary.messages == 5
    assert [(f["index"], f["kind"]) for f in summary.failed] == [
        (1, "fields"),
        (2, "size"),
        (4, "size"),
    ]
    assert "has no x field" in summary.failed[0]["reason"]
    assert summary.failed[1]["reason"].startswith(f"{source}: /points message 2 (t=")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2  # once per kind
    before, after = read_bag(source), read_bag(target)
    assert [m[:3] for m in after] == [m[:3] for m in before]
    clouds_in = [m[3] for m in before if m[0] == "/points"]
    clouds_out = [m[3] for m in after if m[0] == "/points"]
    for i in (1, 2, 4):
        assert clouds_out[i] == clouds_in[i]
    assert "label" in [f.name for f in after[1][4].fields]
    record = json.loads((tmp_path / "out.run.json").read_text())
    assert record["messages_failed"] == 3
    assert [f["kind"] for f in record["failed"]] == ["fields", "size", "size"]
    stamps = [m[2] for m in before if m[0] == "/points"]
    assert [f["timestamp"] for f in record["failed"]] == [stamps[1], stamps[2], stamps[4]]


def test_fields_named_on_the_command_line_and_a_missing_reflectance(tmp_path, predictor, points):
    pts = points[::40]
    named = write_bag(tmp_path / "named", "rosbag2-sqlite3", [_dense(pts, reflectance="strength")])
    summary = label_bag(predictor, named, "/points", tmp_path / "named-out",
                        overrides={"remission": "strength"}, progress=False)  # fmt: skip
    assert summary.ok
    assert summary.field_sources == [{"x": "x", "y": "y", "z": "z", "remission": "strength"}]
    xyz = Cloud([(n, FLOAT32, pts[:, i]) for i, n in enumerate("xyz")])
    bare = write_bag(tmp_path / "bare", "rosbag2-sqlite3", [xyz])
    summary = label_bag(predictor, bare, "/points", tmp_path / "bare-out", progress=False)
    fill = predictor.profile.reflectance_fill
    assert summary.field_sources == [{"x": "x", "y": "y", "z": "z", "remission": f"fill {fill:g}"}]
    out = [m[4] for m in read_bag(tmp_path / "bare-out") if m[0] == "/points"]
    filled = np.column_stack([pts[:, :3], np.full(len(pts), fill)]).astype(np.float32)
    expected, _ = _expected(predictor, _dense(filled))
    np.testing.assert_array_equal(decode(out[0], "out")[1]["label"], expected)


def test_a_failure_leaves_nothing_at_the_target(tmp_path, predictor, points, monkeypatch):
    source = write_bag(tmp_path / "in.bag", "ros1", [_dense(points[::50])] * 3)
    calls = []

    def failing(pred, cloud, times=None):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("the network stopped")
        return label_cloud(pred, cloud, times)

    monkeypatch.setattr(bag_runner, "label_cloud", failing)
    with pytest.raises(RuntimeError, match="the network stopped"):
        label_bag(predictor, source, "/points", tmp_path / "out.bag", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.bag"]


def test_a_missing_topic_writes_nothing(tmp_path, predictor, points):
    source = write_bag(tmp_path / "in", "rosbag2-sqlite3", [_dense(points[::50])])
    with pytest.raises(BagError, match="has no topic '/velodyne'; its topics: /chat"):
        label_bag(predictor, source, "/velodyne", tmp_path / "out", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_an_existing_target_is_refused_before_reading(tmp_path, predictor, points):
    source = write_bag(tmp_path / "in", "rosbag2-sqlite3", [_dense(points[::50])])
    (tmp_path / "out").mkdir()
    with pytest.raises(BagError, match="exists; pass --overwrite"):
        label_bag(predictor, source, "/points", tmp_path / "out", progress=False)
    with pytest.raises(BagError, match="is a folder this command did not write"):
        label_bag(predictor, source, "/points", tmp_path / "out", overwrite=True, progress=False)
    (tmp_path / "out.run.json").write_text("{}")  # an earlier run's record: its own output
    summary = label_bag(predictor, source, "/points", tmp_path / "out", overwrite=True,
                        progress=False)  # fmt: skip
    assert summary.ok and (tmp_path / "out" / "metadata.yaml").is_file()
    assert isinstance(summary.target, Path)
