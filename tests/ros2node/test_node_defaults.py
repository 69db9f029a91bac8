"""`rangeret ros2` with its default QoS (sensor data in), best-effort answers, a renamed node, a
`--field` mapping and no rgb; SIGINT stops it with exit 0."""

from __future__ import annotations

import numpy as np
import pytest

from rangeret.io.pointcloud2 import FLOAT32, FLOAT64, UINT16, UINT32, decode
from rangeret.io.scans import KITTI_RECORD, read_scan
from tests.support.ros import domain_id_for, drive_node, make_cloud
from tests.support.workers import small_weights


@pytest.fixture(scope="module")
def drive(tmp_path_factory, real_scan_path):
    points = read_scan(real_scan_path, KITTI_RECORD)[::40]
    cloud = make_cloud(
        {
            "x": (FLOAT32, points[:, 0]),
            "y": (FLOAT32, points[:, 1]),
            "z": (FLOAT32, points[:, 2]),
            "refl": (FLOAT32, points[:, 3]),
            "ring": (UINT16, np.arange(len(points)) % 64),
            "t": (FLOAT64, np.linspace(0, 0.1, len(points))),
        },
        stamp=(42, 7),
    )
    weights = small_weights(tmp_path_factory.mktemp("weights"))
    args = ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu",
            "--report-every", "0.3", "--output-qos", "sensor", "--field", "remission=refl",
            "--input-topic", "lidar/points", "--output-topic", "lidar/labelled",
            "--ros-args", "-r", "__node:=labeller"]  # fmt: skip
    result = drive_node(
        tmp_path_factory.mktemp("node"),
        args,
        [cloud],
        domain_id=domain_id_for(2),
        stop_signal="SIGINT",
        input_topic="lidar/points",
        output_topic="lidar/labelled",
        output_reliable=False,
    )
    return cloud, result


def test_the_answer_keeps_every_field_and_adds_label_and_confidence_only(drive):
    cloud, result = drive
    answer = result.answers[0]
    assert answer.stamp == (42, 7)
    assert [f.name for f in answer.fields] == [
        *(f.name for f in cloud.fields),
        "label",
        "confidence",
    ]
    got, sent = decode(answer, "answer")[1], decode(cloud, "sent")[1]
    for name in sent:
        np.testing.assert_array_equal(got[name], sent[name], err_msg=name)
    assert got["label"].dtype == np.uint32 and len(np.unique(got["label"])) > 1
    assert [f.datatype for f in answer.fields[-2:]] == [UINT32, FLOAT32]


def test_the_node_runs_under_its_remapped_name_with_the_options_given(drive):
    _, result = drive
    assert result.status["name"] == "labeller: labelling"
    values = result.diagnostics
    assert values["input_topic"] == "/lidar/points"
    assert values["input_qos"] == "sensor data QoS (best effort, keep last 5)"
    assert values["output_qos"] == "sensor data QoS (best effort, keep last 5)"
    assert values["fields"] == "remission=refl"
    assert values["bad"] == "0" and int(values["labelled"]) >= 1


def test_sigint_stops_the_node_cleanly(drive):
    _, result = drive
    assert result.returncode == 0, result.log[-3000:]
    assert "Traceback" not in result.log and "interrupted" not in result.log
    assert "stopped: the node is destroyed and ROS 2 shut down" in result.log
