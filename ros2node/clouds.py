"""A PointCloud2 message as the profile's point record, and the labelled message built from it.

The record is read with `rangeret.io.pointcloud2.read_cloud` (any datatype, byte order, point
step, padding or row step); the answer keeps the input's header, points, order and every field,
and adds `label` (UINT32 raw id) and `confidence` (FLOAT32), with panoptic segmentation
`instance` (UINT32), and with colours a packed `rgb` (FLOAT32), after them (`append_labels`), as
a labelled bag's clouds do.
"""

from __future__ import annotations

import array
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from rangeret.dataset.labels import SEMANTIC_MASK
from rangeret.dataset.profiles import DatasetProfile
from rangeret.inference.results import ScanPrediction
from rangeret.io.point_fields import RecordPoints
from rangeret.io.pointcloud2 import CloudLayout, append_labels, pack_rgb, read_cloud
from rangeret.io.scans import PointRecord


@dataclass(frozen=True)
class FieldMapping:
    """How a message's fields fill the profile's record."""

    record: PointRecord
    reflectance_fill: float
    overrides: Mapping[str, str]


def cloud_record(msg: Any, source: str, mapping: FieldMapping) -> tuple[CloudLayout, RecordPoints]:
    """The message's layout and its points as the record; a bad message is a
    `CloudMessageError` or a `PointFieldsError` naming `source`."""
    return read_cloud(
        msg,
        source,
        record=mapping.record,
        reflectance_fill=mapping.reflectance_fill,
        overrides=mapping.overrides,
    )


def palette_of(profile: DatasetProfile) -> np.ndarray:
    """The packed `rgb` value (float32, see `pack_rgb`) of every 16-bit value the `label` field
    holds, made once so each message needs one look-up per point: a raw id's palette colour, or
    a class's where the profile's benchmark takes classes (nuScenes)."""
    from rangeret.evaluation.view import raw_palette

    config = profile.labels
    if profile.benchmark.predictions != "class":
        return pack_rgb(raw_palette(config))
    colours = np.zeros((SEMANTIC_MASK + 1, 3), dtype=np.uint8)
    classes = config.class_rgb()
    colours[: len(classes)] = classes
    return pack_rgb(colours)


def labelled_message(
    msg: Any, layout: CloudLayout, labels: ScanPrediction, palette: np.ndarray | None = None
) -> PointCloud2:
    """The answer to `msg`: its header and points with `label` (`labels.labels`, the raw ids),
    `confidence`, given panoptic segmentation's `labels.instances` `instance`, and given a
    `palette_of` table `rgb` added."""
    rgb = None if palette is None else palette[labels.labels & SEMANTIC_MASK]
    fields, step, data = append_labels(
        layout, msg.data, labels.labels, labels.confidence, rgb, labels.instances
    )
    out = PointCloud2()
    out.header = msg.header
    out.height = layout.height
    out.width = layout.width
    out.fields = [
        PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in fields
    ]
    out.is_bigendian = layout.is_bigendian
    out.point_step = step
    out.row_step = step * layout.width
    buffer = array.array("B")
    buffer.frombytes(data)
    out.data = buffer
    out.is_dense = bool(msg.is_dense)
    return out
