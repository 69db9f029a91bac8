"""The byte layout of a `sensor_msgs/PointCloud2` message, read and written with numpy alone.

A PointCloud2 holds `height * width` points of `point_step` bytes each (rows `row_step` bytes
apart), whose named fields lie at given offsets with one of eight datatypes, in either byte order.
`decode` checks a message's layout and gives each field as an array; `append_fields` gives the
message's bytes with new fields after the old ones (every input field and point kept, in order).
Messages from rclpy and from `rosbags` are read alike: only their attributes are used, so this
module needs neither.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rangeret.exceptions import InputError
from rangeret.io.point_fields import RecordPoints, to_record
from rangeret.io.scans import PointRecord

#: `sensor_msgs/PointField` datatypes and their numpy types (byte order applied per message).
DATATYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)


class CloudMessageError(InputError, ValueError):
    """A PointCloud2 whose layout is wrong; `kind` is a short key of the problem (one log line
    per kind), the message names the source and the problem."""

    def __init__(self, source: str, kind: str, problem: str) -> None:
        self.kind = kind
        super().__init__(f"{source}: {problem}")


@dataclass(frozen=True)
class CloudField:
    """One `sensor_msgs/PointField`."""

    name: str
    offset: int
    datatype: int
    count: int = 1

    @property
    def size(self) -> int:
        """Bytes of the field in one point."""
        return np.dtype(DATATYPES[self.datatype]).itemsize * self.count


@dataclass(frozen=True)
class CloudLayout:
    """What a PointCloud2's header fields say about its bytes."""

    fields: tuple[CloudField, ...]
    height: int
    width: int
    point_step: int
    row_step: int
    is_bigendian: bool

    @property
    def num_points(self) -> int:
        """Points of the cloud (`height * width`)."""
        return self.height * self.width

    def names(self) -> list[str]:
        """Field names, in the message's order."""
        return [f.name for f in self.fields]


def layout_of(msg: Any) -> CloudLayout:
    """The layout of a PointCloud2 message (an rclpy or a rosbags one)."""
    return CloudLayout(
        fields=tuple(
            CloudField(str(f.name), int(f.offset), int(f.datatype), int(f.count))
            for f in msg.fields
        ),
        height=int(msg.height),
        width=int(msg.width),
        point_step=int(msg.point_step),
        row_step=int(msg.row_step),
        is_bigendian=bool(msg.is_bigendian),
    )


def check_layout(layout: CloudLayout, data_size: int, source: str) -> None:
    """CloudMessageError unless the fields fit the point step and the data holds the points."""
    if layout.point_step < 1 and layout.num_points > 0:
        raise CloudMessageError(
            source,
            "point_step",
            f"point_step is {layout.point_step} for {layout.num_points} points",
        )
    seen: set[str] = set()
    for f in layout.fields:
        if f.datatype not in DATATYPES:
            raise CloudMessageError(
                source, "datatype", f"field {f.name!r} has unknown datatype {f.datatype}"
            )
        if f.count < 1:
            raise CloudMessageError(source, "count", f"field {f.name!r} has count {f.count}")
        if f.name in seen:
            raise CloudMessageError(source, "duplicate", f"field {f.name!r} appears twice")
        seen.add(f.name)
        if f.offset < 0 or f.offset + f.size > layout.point_step:
            raise CloudMessageError(
                source,
                "point_step",
                f"field {f.name!r} (offset {f.offset}, {f.size} bytes) does not fit in "
                f"point_step {layout.point_step}",
            )
    if layout.row_step < layout.width * layout.point_step:
        raise CloudMessageError(
            source,
            "row_step",
            f"row_step {layout.row_step} is less than width {layout.width} x point_step "
            f"{layout.point_step}",
        )
    if data_size != layout.height * layout.row_step:
        raise CloudMessageError(
            source,
            "size",
            f"holds {data_size} bytes of data, but height {layout.height} x row_step "
            f"{layout.row_step} is {layout.height * layout.row_step}",
        )


def _points_bytes(layout: CloudLayout, data: Any) -> np.ndarray:
    """The points' bytes as a uint8 (N, point_step) array (row padding dropped)."""
    raw = np.frombuffer(memoryview(data), dtype=np.uint8)
    if layout.row_step == layout.width * layout.point_step:
        return raw.reshape(layout.num_points, layout.point_step)
    rows = raw.reshape(layout.height, layout.row_step)[:, : layout.width * layout.point_step]
    return rows.reshape(layout.num_points, layout.point_step)


def _dtype(layout: CloudLayout, fields: Sequence[CloudField]) -> np.dtype:
    order = ">" if layout.is_bigendian else "<"
    return np.dtype(
        {
            "names": [f.name for f in fields],
            "formats": [
                (order + DATATYPES[f.datatype], (f.count,)) if f.count > 1 else
                order + DATATYPES[f.datatype]
                for f in fields
            ],
            "offsets": [f.offset for f in fields],
            "itemsize": layout.point_step,
        }
    )  # fmt: skip


def decode(msg: Any, source: str) -> tuple[CloudLayout, dict[str, np.ndarray]]:
    """The layout of a PointCloud2 and each of its fields as an array (N,) or (N, count) in
    native byte order, points in the message's order; a bad layout is a CloudMessageError."""
    layout = layout_of(msg)
    data = msg.data
    check_layout(layout, memoryview(data).nbytes, source)
    points = _points_bytes(layout, data)
    records = points.reshape(-1).view(_dtype(layout, layout.fields))
    return layout, {
        f.name: records[f.name].astype(records[f.name].dtype.newbyteorder("="))
        for f in layout.fields
    }


def append_fields(
    layout: CloudLayout, data: Any, new: Mapping[str, tuple[int, np.ndarray]]
) -> tuple[list[CloudField], int, bytes]:
    """The message's points with `new` fields ({name: (datatype, values)}) after its own.

    Returns the fields, the new point step and the dense bytes (row_step = width * point_step).
    An input field of a new field's name is replaced by it; every other one is kept as it was.
    """
    kept = [f for f in layout.fields if f.name not in new]
    start = -(-layout.point_step // 4) * 4
    added: list[CloudField] = []
    offset = start
    for name, (datatype, _values) in new.items():
        added.append(CloudField(name, offset, datatype, 1))
        offset += np.dtype(DATATYPES[datatype]).itemsize
    step = -(-offset // 4) * 4
    out = np.zeros((layout.num_points, step), dtype=np.uint8)
    out[:, : layout.point_step] = _points_bytes(layout, data)
    out_layout = CloudLayout(
        tuple(added), layout.height, layout.width, step, step * layout.width, layout.is_bigendian
    )
    records = out.reshape(-1).view(_dtype(out_layout, added))
    for f, (_datatype, values) in zip(added, new.values(), strict=True):
        records[f.name] = values
    return kept + added, step, out.tobytes()


def read_cloud(
    msg: Any,
    source: str,
    *,
    record: PointRecord,
    reflectance_fill: float,
    overrides: Mapping[str, str] | None = None,
) -> tuple[CloudLayout, RecordPoints]:
    """A PointCloud2's layout and its points as `record` (see `to_record`): what every reader
    of messages (a bag's, a topic's) labels. A bad message is a CloudMessageError or a
    PointFieldsError naming `source`."""
    layout, columns = decode(msg, source)
    points = to_record(
        columns,
        record=record,
        source=source,
        reflectance_fill=reflectance_fill,
        overrides=overrides,
    )
    return layout, points


def append_labels(
    layout: CloudLayout,
    data: Any,
    labels: np.ndarray,
    confidence: np.ndarray,
    rgb: np.ndarray | None = None,
    instances: np.ndarray | None = None,
) -> tuple[list[CloudField], int, bytes]:
    """The message's points with `label` (UINT32 raw id), `confidence` (FLOAT32), given
    panoptic segmentation's `instances` `instance` (UINT32, 0 for stuff), and given packed
    colours `rgb` (FLOAT32), in that order after its own fields (see `append_fields`)."""
    new: dict[str, tuple[int, np.ndarray]] = {
        "label": (UINT32, labels),
        "confidence": (FLOAT32, confidence),
    }
    if instances is not None:
        new["instance"] = (UINT32, instances)
    if rgb is not None:
        new["rgb"] = (FLOAT32, rgb)
    return append_fields(layout, data, new)


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours as PCL's packed `rgb` float32 field (0x00RRGGBB bits), which RViz
    and Foxglove colour points by."""
    rgb = np.asarray(rgb, dtype=np.uint32)
    packed = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
    return packed.astype(np.uint32).view(np.float32)
