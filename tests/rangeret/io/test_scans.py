"""Scan and label files: reading, writing and every kind of bad input."""

from __future__ import annotations

import numpy as np
import pytest

from rangeret.io.scans import (
    KITTI_RECORD,
    ScanFormatError,
    parse_scan,
    read_labels,
    read_scan,
    scan_num_points,
    write_labels,
    write_scan,
)


def test_real_scan_reads_as_float32_points(real_scan_path, real_label_path):
    points = read_scan(real_scan_path)
    assert points.shape == (123_389, 4)
    assert points.dtype == np.float32
    assert points.flags.writeable
    labels = read_labels(real_label_path, num_points=len(points))
    assert labels.dtype == np.uint32 and labels.shape == (123_389,)
    assert scan_num_points(real_scan_path, record=KITTI_RECORD) == 123_389


def test_round_trip(tmp_path):
    points = np.random.default_rng(0).normal(size=(10, 4)).astype(np.float32)
    write_scan(tmp_path / "a" / "000000.bin", points, record=KITTI_RECORD)
    np.testing.assert_array_equal(read_scan(tmp_path / "a" / "000000.bin"), points)
    labels = np.array([10, 40 | (7 << 16), 252], dtype=np.uint32)
    write_labels(tmp_path / "x.label", labels)
    np.testing.assert_array_equal(read_labels(tmp_path / "x.label"), labels)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["000000.bin", "a", "x.label"]


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        (b"", "empty"),
        (b"\x00" * 17, "not a multiple of 16"),
        (np.array([[1, 2, 3, 0.5], [np.nan, 0, 0, 0]], np.float32).tobytes(), "non-finite"),
        (np.array([[1, 2, np.inf, 0.5]], np.float32).tobytes(), "non-finite"),
    ],
)
def test_bad_scans_name_file_and_problem(tmp_path, payload, message):
    path = tmp_path / "bad.bin"
    path.write_bytes(payload)
    with pytest.raises(ScanFormatError) as info:
        read_scan(path)
    assert str(path) in str(info.value)
    assert message in str(info.value)


def test_non_finite_error_gives_point_index():
    data = np.zeros((5, 4), np.float32)
    data[3, 1] = np.nan
    with pytest.raises(ScanFormatError, match="point index 3"):
        parse_scan(data.tobytes(), "upload", record=KITTI_RECORD)


def test_label_count_mismatch_names_file(tmp_path):
    path = tmp_path / "000001.label"
    write_labels(path, np.zeros(5, np.uint32))
    with pytest.raises(ScanFormatError, match=r"000001\.label: holds 5 labels but the scan has 6"):
        read_labels(path, num_points=6)
    path.write_bytes(b"\x00" * 6)
    with pytest.raises(ScanFormatError, match="not a multiple of 4"):
        read_labels(path)


def test_truncated_scan_size_check_without_reading(tmp_path):
    path = tmp_path / "t.bin"
    path.write_bytes(b"\x00" * 33)
    with pytest.raises(ScanFormatError, match=r"t\.bin"):
        scan_num_points(path, record=KITTI_RECORD)


def test_write_rejects_bad_shapes(tmp_path):
    with pytest.raises(ValueError, match="one-dimensional"):
        write_labels(tmp_path / "l.label", np.zeros((2, 2), np.uint32))
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        write_scan(tmp_path / "s.bin", np.zeros((3, 3), np.float32), record=KITTI_RECORD)
    with pytest.raises(ValueError, match="uint32"):
        write_labels(tmp_path / "l.label", np.array([-1]))
