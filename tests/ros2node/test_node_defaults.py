"""`rangeret ros2` with its default QoS (sensor data in) and transport, best-effort answers, a
renamed node, a `--field` mapping and no rgb: a full-size cloud published best effort, as a
driver does, is labelled on its first send; a publisher matched for 10 s with nothing arrived
gets a warning naming what to change; SIGINT stops it with exit 0."""

from __future__ import annotations

import numpy as np
import pytest

from rangeret.io.pointcloud2 import FLOAT32, FLOAT64, UINT16, UINT32, decode
from rangeret.io.scans import KITTI_RECORD, read_scan
from tests.support.ros import domain_id_for, drive_node, make_cloud
from tests.support.workers import small_weights

#: The driver stays matched and silent until the node warns, at most this long (seconds).
SILENT_S = 30.0
#: The node's warning about a matched publisher whose messages never arrive.
SILENCE_WARNING = "but no message has arrived"


@pytest.fixture(scope="module")
def drive(tmp_path_factory, real_scan_path):
    points = read_scan(real_scan_path, KITTI_RECORD)
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
        input_reliable=False,
        resend=False,
        answer_s=30.0,
        idle_s=SILENT_S,
        idle_until=SILENCE_WARNING,
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


def test_a_full_size_best_effort_cloud_is_labelled_on_its_first_send(drive):
    cloud, result = drive
    assert cloud.width == 123389 and len(cloud.data) > 3_000_000
    assert result.extra["sends"] == {"0": 1}, result.log[-3000:]
    assert 0 in result.answers and result.extra["answer_s"]["0"] < 30.0


def test_the_node_applies_its_own_transport_profile_when_the_user_set_none(drive):
    _, result = drive
    transport = result.diagnostics["transport"]
    assert transport.startswith("the node's Fast DDS profile (UDP receive buffer 8 MiB")
    assert f"DDS transport: {transport}" in result.log


def test_a_matched_silent_publisher_gets_one_warning_naming_what_to_change(drive):
    _, result = drive
    warnings = [line for line in result.log.splitlines() if SILENCE_WARNING in line]
    assert len(warnings) == 1, result.log[-3000:]
    assert "/lidar/points: 1 matched publisher for 10 s" in warnings[0]
    assert "They publish best effort" in warnings[0]
    assert "--input-qos reliable" in warnings[0] and "docs/ros2.md" in warnings[0]
