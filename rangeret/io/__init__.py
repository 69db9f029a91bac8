"""Files and messages: scans and labels, point-cloud files (PCD, PLY, LAS and LAZ) and their named
fields as a profile's record, bags (rosbag2 and ROS 1), PointCloud2 messages, atomic writes,
reproducible zips, bounded YAML and `run.json`.

Scan and label reading is re-exported here (`rangeret.io.read_scan`), its long-standing path.
"""

from rangeret.io.scans import (
    KITTI_RECORD,
    LABEL_BYTES,
    LABEL_DTYPE,
    POINT_BYTES,
    SCAN_DTYPE,
    PointRecord,
    ScanFormatError,
    parse_scan,
    read_confidence,
    read_labels,
    read_scan,
    scan_num_points,
    write_confidence,
    write_labels,
    write_scan,
)

__all__ = [
    "KITTI_RECORD",
    "LABEL_BYTES",
    "LABEL_DTYPE",
    "POINT_BYTES",
    "SCAN_DTYPE",
    "PointRecord",
    "ScanFormatError",
    "parse_scan",
    "read_confidence",
    "read_labels",
    "read_scan",
    "scan_num_points",
    "write_confidence",
    "write_labels",
    "write_scan",
]
