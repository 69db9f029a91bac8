"""Small bags written with `rosbags` in each format: PointCloud2 clouds (any fields, padding, byte
order, organised rows), std_msgs/String and sensor_msgs/Imu messages, with QoS or latching."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

from rangeret.io.pointcloud2 import DATATYPES

FORMATS = ("rosbag2-sqlite3", "rosbag2-mcap", "ros1")
#: The QoS profile the String topic is recorded with in rosbag2 bags (kept by a copy).
CHAT_QOS = Qos(
    QosHistory.KEEP_LAST,
    7,
    QosReliability.RELIABLE,
    QosDurability.TRANSIENT_LOCAL,
    QosTime(0, 0),
    QosTime(0, 0),
    QosLiveliness.AUTOMATIC,
    QosTime(0, 0),
    avoid_ros_namespace_conventions=False,
)


@dataclass
class Cloud:
    """A PointCloud2 to write: fields (name, datatype, values (N,) or (N, count)) in the order
    and at the offsets given (None: packed after the previous), with extra bytes per point and
    per row, rows, byte order, stamp and frame."""

    fields: Sequence[tuple[str, int, np.ndarray]]
    offsets: Sequence[int] | None = None
    point_step: int | None = None
    row_pad: int = 0
    height: int = 1
    bigendian: bool = False
    stamp: tuple[int, int] = (1_600_000_000, 5)
    frame: str = "velodyne"

    @property
    def num_points(self) -> int:
        return len(self.fields[0][2])


def cloud_bytes(cloud: Cloud) -> tuple[list[tuple[str, int, int, int]], int, int, np.ndarray]:
    """The cloud's PointField tuples (name, offset, datatype, count), point step, row step and
    data bytes."""
    order = ">" if cloud.bigendian else "<"
    fields, offset = [], 0
    for i, (name, datatype, values) in enumerate(cloud.fields):
        count = 1 if np.ndim(values) == 1 else np.shape(values)[1]
        if cloud.offsets is not None:
            offset = cloud.offsets[i]
        fields.append((name, offset, datatype, count))
        offset += np.dtype(DATATYPES[datatype]).itemsize * count
    step = cloud.point_step or offset
    dtype = np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [(order + DATATYPES[f[2]], (f[3],)) if f[3] > 1 else order + DATATYPES[f[2]]
                        for f in fields],
            "offsets": [f[1] for f in fields],
            "itemsize": step,
        }
    )  # fmt: skip
    records = np.zeros(cloud.num_points, dtype=dtype)
    for name, _datatype, values in cloud.fields:
        records[name] = values
    width = cloud.num_points // cloud.height
    rows = records.view(np.uint8).reshape(cloud.height, width * step)
    row_step = width * step + cloud.row_pad
    padded = np.full((cloud.height, row_step), 0xAB, dtype=np.uint8)
    padded[:, : width * step] = rows
    return fields, step, row_step, padded.reshape(-1)


def pointcloud2(store, cloud: Cloud):  # type: ignore[no-untyped-def]
    """The cloud as a PointCloud2 object of `store` (a ROS 1 or ROS 2 typestore)."""
    t = store.types
    fields, step, row_step, data = cloud_bytes(cloud)
    return t["sensor_msgs/msg/PointCloud2"](
        header=_header(store, cloud.stamp, cloud.frame),
        height=cloud.height,
        width=cloud.num_points // cloud.height,
        fields=[
            t["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=c)
            for n, o, d, c in fields
        ],
        is_bigendian=cloud.bigendian,
        point_step=step,
        row_step=row_step,
        data=data,
        is_dense=False,
    )


def _header(store, stamp: tuple[int, int], frame: str):  # type: ignore[no-untyped-def]
    t = store.types
    time = t["builtin_interfaces/msg/Time"](sec=stamp[0], nanosec=stamp[1])
    if "seq" in t["std_msgs/msg/Header"].__dataclass_fields__:
        return t["std_msgs/msg/Header"](seq=3, stamp=time, frame_id=frame)
    return t["std_msgs/msg/Header"](stamp=time, frame_id=frame)


def imu(store, k: int):  # type: ignore[no-untyped-def]
    """An Imu message whose values depend on `k`."""
    t = store.types
    vec = t["geometry_msgs/msg/Vector3"]
    cov = np.arange(9, dtype=np.float64) + k
    return t["sensor_msgs/msg/Imu"](
        header=_header(store, (1_600_000_000 + k, 7), "imu"),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=cov,
        angular_velocity=vec(x=0.1 * k, y=0.2, z=0.3),
        angular_velocity_covariance=cov,
        linear_acceleration=vec(x=9.8, y=0.0, z=-0.1 * k),
        linear_acceleration_covariance=cov,
    )


def typestore(fmt: str):  # type: ignore[no-untyped-def]
    """The typestore messages of a bag of kind `fmt` are written with."""
    return get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)


def write_bag(
    path: Path, fmt: str, clouds: Sequence[Cloud | Callable], topic: str = "/points"
) -> Path:
    """A bag at `path` with each cloud on `topic` (0.1 s apart; a callable is called with the
    typestore for its PointCloud2 object, a broken one say), and a String topic and an Imu
    topic between them."""
    store = typestore(fmt)
    cloud_type, chat_type, imu_type = (
        "sensor_msgs/msg/PointCloud2", "std_msgs/msg/String", "sensor_msgs/msg/Imu",
    )  # fmt: skip
    encode = store.serialize_ros1 if fmt == "ros1" else store.serialize_cdr
    if fmt == "ros1":
        writer = Ros1Writer(path)
    else:
        storage = StoragePlugin.MCAP if fmt == "rosbag2-mcap" else StoragePlugin.SQLITE3
        writer = Ros2Writer(path, version=9, storage_plugin=storage)
    with writer:
        if fmt == "ros1":
            points = writer.add_connection(topic, cloud_type, typestore=store)
            chat = writer.add_connection(
                "/chat", chat_type, typestore=store, callerid="/talker", latching=1
            )
            motion = writer.add_connection("/imu", imu_type, typestore=store)
        else:
            points = writer.add_connection(topic, cloud_type, typestore=store)
            chat = writer.add_connection(
                "/chat", chat_type, typestore=store, offered_qos_profiles=[CHAT_QOS]
            )
            motion = writer.add_connection("/imu", imu_type, typestore=store)
        t0 = 1_600_000_000_000_000_000
        writer.write(chat, t0 - 1, encode(store.types[chat_type](data="start"), chat_type))
        for k, cloud in enumerate(clouds):
            t = t0 + k * 100_000_000
            msg = pointcloud2(store, cloud) if isinstance(cloud, Cloud) else cloud(store)
            writer.write(points, t, encode(msg, cloud_type))
            writer.write(motion, t + 1, encode(imu(store, k), imu_type))
            writer.write(chat, t + 2, encode(store.types[chat_type](data=f"cloud {k}"), chat_type))
    return path


def read_bag(path: Path) -> list[tuple[str, str, int, bytes, object]]:
    """Every message of a bag as (topic, type, timestamp, raw bytes, decoded message)."""
    with AnyReader([path]) as reader:
        return [
            (c.topic, c.msgtype, t, bytes(raw), reader.deserialize(raw, c.msgtype))
            for c, t, raw in reader.messages()
        ]


def connections(path: Path) -> dict[str, object]:
    """The connections of a bag by topic (rosbag2 QoS profiles or ROS 1 caller id, latching)."""
    with AnyReader([path]) as reader:
        return {c.topic: c for c in reader.connections}
