"""Bags through `rosbags`: which kind a path is, copies that keep every message, timestamp and
connection, conversions between ROS 1 and rosbag2, and a target that appears only complete."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from rosbags.interfaces import ConnectionExtRosbag1, ConnectionExtRosbag2, QosDurability
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer

from rangeret.io.bags import (
    BagError,
    atomic_bag,
    bag_format,
    check_target,
    open_bag,
    run_record_path,
)
from rangeret.io.pointcloud2 import FLOAT32, CloudMessageError
from tests.support.bags import CHAT_QOS, FORMATS, Cloud, connections, read_bag, typestore, write_bag


def _name(fmt: str, stem: str) -> str:
    return stem + (".bag" if fmt == "ros1" else "")


def _cloud(n: int = 20, seed: int = 0) -> Cloud:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-20, 20, size=(n, 4)).astype(np.float32)
    return Cloud(
        [(name, FLOAT32, pts[:, i]) for i, name in enumerate(["x", "y", "z", "intensity"])]
    )


@pytest.fixture(params=FORMATS)
def fmt(request) -> str:
    return request.param


def _copy(source: Path, target: Path, fmt: str, *, overwrite=False, fail=False) -> None:
    """Copy every message of `source` into a new bag at `target`; with `fail`, stop with an
    error after the first message."""
    with (
        open_bag(source) as bag,
        atomic_bag(target, fmt, overwrite=overwrite) as path,
        bag.copy_to(path, fmt) as out,
    ):
        for conn, t, raw in bag.messages():
            out.write(conn, t, raw)
            if fail:
                raise RuntimeError("stop")


def test_bag_format_tells_each_kind(tmp_path, fmt):
    path = write_bag(tmp_path / _name(fmt, "in"), fmt, [_cloud()])
    assert bag_format(path) == fmt


def test_paths_that_are_no_bag_are_one_line_each(tmp_path):
    (tmp_path / "folder").mkdir()
    (tmp_path / "scan.bin").write_bytes(b"\0" * 64)
    ros1 = write_bag(tmp_path / "in.bag", "ros1", [_cloud()])
    renamed = ros1.rename(tmp_path / "in.dat")
    cases = {
        tmp_path / "folder": "a folder without metadata.yaml is not a rosbag2 bag",
        tmp_path / "scan.bin": "neither a rosbag2 folder (with metadata.yaml) nor a ROS 1 bag",
        renamed: "a ROS 1 bag's name must end in .bag",
        tmp_path / "missing.bag": "no such bag",
    }
    for path, words in cases.items():
        with pytest.raises(BagError, match=re.escape(words)) as err:
            bag_format(path)
        assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_a_target_name_must_fit_its_kind_and_an_existing_one_needs_overwrite(tmp_path):
    with pytest.raises(BagError, match=r"must end in \.bag"):
        check_target(tmp_path / "out", "ros1", overwrite=False)
    with pytest.raises(BagError, match=r"must not end in \.bag"):
        check_target(tmp_path / "out.bag", "rosbag2-mcap", overwrite=False)
    (tmp_path / "out").mkdir()
    with pytest.raises(BagError, match="exists; pass --overwrite"):
        check_target(tmp_path / "out", "rosbag2-sqlite3", overwrite=False)
    with pytest.raises(BagError, match="is a folder this command did not write"):
        check_target(tmp_path / "out", "rosbag2-sqlite3", overwrite=True)
    run_record_path(tmp_path / "out").write_text("{}")  # one this command wrote
    check_target(tmp_path / "out", "rosbag2-sqlite3", overwrite=True)
    with pytest.raises(BagError, match="cannot replace the bag it is read from"):
        check_target(tmp_path / "out", "rosbag2-sqlite3", overwrite=True, source=tmp_path / "out")
    assert run_record_path(tmp_path / "out.bag") == tmp_path / "out.bag.run.json"


def test_a_copy_in_the_same_kind_keeps_every_byte_timestamp_and_connection(tmp_path, fmt):
    source = write_bag(tmp_path / _name(fmt, "in"), fmt, [_cloud(seed=k) for k in range(3)])
    target = tmp_path / _name(fmt, "out")
    _copy(source, target, fmt)
    assert bag_format(target) == fmt
    assert [m[:4] for m in read_bag(target)] == [m[:4] for m in read_bag(source)]
    before, after = connections(source), connections(target)
    assert sorted(after) == ["/chat", "/imu", "/points"]
    for topic, conn in before.items():
        copied = after[topic]
        assert (copied.msgtype, copied.msgdef, copied.digest, copied.ext) == (
            conn.msgtype, conn.msgdef, conn.digest, conn.ext,
        )  # fmt: skip
    chat = after["/chat"].ext
    if fmt == "ros1":
        assert chat == ConnectionExtRosbag1("/talker", 1)
    else:
        assert chat.offered_qos_profiles == [CHAT_QOS]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([source.name, target.name])


@pytest.mark.parametrize(
    ("fmt_in", "fmt_out"),
    [("ros1", "rosbag2-sqlite3"), ("rosbag2-mcap", "ros1"), ("rosbag2-sqlite3", "rosbag2-mcap")],
)
def test_a_conversion_keeps_every_message_and_timestamp(tmp_path, fmt_in, fmt_out):
    source = write_bag(tmp_path / _name(fmt_in, "in"), fmt_in, [_cloud(seed=k) for k in range(2)])
    target = tmp_path / _name(fmt_out, "out")
    _copy(source, target, fmt_out)
    assert bag_format(target) == fmt_out
    before, after = read_bag(source), read_bag(target)
    assert [m[:3] for m in after] == [m[:3] for m in before]
    for (_, msgtype, _, _, a), (_, _, _, _, b) in zip(before, after, strict=True):
        if msgtype == "std_msgs/msg/String":
            assert a.data == b.data
        else:
            assert (a.header.stamp.sec, a.header.stamp.nanosec, a.header.frame_id) == (
                b.header.stamp.sec, b.header.stamp.nanosec, b.header.frame_id,
            )  # fmt: skip
        if msgtype == "sensor_msgs/msg/Imu":
            np.testing.assert_array_equal(a.orientation_covariance, b.orientation_covariance)
            assert a.linear_acceleration.z == b.linear_acceleration.z
        if msgtype == "sensor_msgs/msg/PointCloud2":
            np.testing.assert_array_equal(a.data, b.data)
    if fmt_in == "rosbag2-sqlite3":  # rosbag2 to rosbag2: the bytes themselves
        assert [m[3] for m in after] == [m[3] for m in before]
    chat = connections(target)["/chat"].ext
    if fmt_out == "ros1":
        assert chat.latching == 1  # the transient-local QoS profile
    else:
        assert isinstance(chat, ConnectionExtRosbag2)
        assert chat.offered_qos_profiles[0].durability == QosDurability.TRANSIENT_LOCAL


def test_a_failed_copy_leaves_nothing_and_an_old_target_as_it_was(tmp_path):
    source = write_bag(tmp_path / "in", "rosbag2-sqlite3", [_cloud(), _cloud()])
    target = tmp_path / "out"
    with pytest.raises(RuntimeError, match="stop"):
        _copy(source, target, "rosbag2-sqlite3", fail=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]
    target.mkdir()
    (target / "old").write_text("kept")
    run_record_path(target).write_text("{}")  # an earlier run's, so --overwrite may replace it
    with pytest.raises(RuntimeError, match="stop"):
        _copy(source, target, "rosbag2-sqlite3", overwrite=True, fail=True)
    assert (target / "old").read_text() == "kept"
    _copy(source, target, "rosbag2-sqlite3", overwrite=True)
    assert not (target / "old").exists() and bag_format(target) == "rosbag2-sqlite3"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "out", "out.run.json"]


def test_a_compressed_rosbag2_bag_is_copied_compressed_alike(tmp_path):
    store = typestore("rosbag2-sqlite3")
    source = tmp_path / "in"
    writer = Ros2Writer(source, version=9, storage_plugin=StoragePlugin.SQLITE3)
    writer.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    writer.set_custom_data("vehicle", "test-car")
    with writer:
        conn = writer.add_connection("/chat", "std_msgs/msg/String", typestore=store)
        for k in range(3):
            msg = store.types["std_msgs/msg/String"](data=f"m{k}" * 50)
            writer.write(conn, 10 + k, store.serialize_cdr(msg, "std_msgs/msg/String"))
    target = tmp_path / "out"
    _copy(source, target, "rosbag2-sqlite3")
    meta = (target / "metadata.yaml").read_text()
    assert "compression_mode: message" in meta and "vehicle: test-car" in meta
    assert [m[:4] for m in read_bag(target)] == [m[:4] for m in read_bag(source)]


def test_the_topic_to_label_must_be_there_and_hold_clouds(tmp_path):
    source = write_bag(tmp_path / "in.bag", "ros1", [_cloud()])
    with open_bag(source) as bag:
        assert bag.cloud_topic("/points").count == 1
        with pytest.raises(BagError) as err:
            bag.cloud_topic("/velodyne_points")
        assert str(err.value) == (
            f"{source}: has no topic '/velodyne_points'; its topics: /chat (std_msgs/msg/String), "
            "/imu (sensor_msgs/msg/Imu), /points (sensor_msgs/msg/PointCloud2)"
        )
        with pytest.raises(BagError, match="topic /imu holds sensor_msgs/msg/Imu, not sensor_msgs"):
            bag.cloud_topic("/imu")


def test_bytes_that_are_no_message_are_a_cloud_message_error(tmp_path):
    source = write_bag(tmp_path / "in", "rosbag2-mcap", [_cloud()])
    with open_bag(source) as bag, pytest.raises(CloudMessageError) as err:
        bag.decode(b"\0\1\0\0\5", "sensor_msgs/msg/PointCloud2", "in: /points message 0")
    assert err.value.kind == "deserialize"
    assert str(err.value).startswith("in: /points message 0: cannot be read as")


def test_a_broken_bag_is_one_line(tmp_path):
    source = write_bag(tmp_path / "in", "rosbag2-sqlite3", [_cloud()])
    (source / "in.db3").write_bytes(b"not a database")
    with (
        pytest.raises(BagError, match="cannot be opened as a rosbag2-sqlite3 bag"),
        open_bag(source),
    ):
        pass
