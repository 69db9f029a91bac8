"""Reading and writing SemanticKITTI scan (`.bin`) and label (`.label`) files, with validation.

A scan is little-endian float32 records (x, y, z, remission), 16 bytes per point. A label file is
one little-endian uint32 per point: the low 16 bits are the raw semantic id, the high 16 bits the
instance id. Every reader checks what it reads and raises `ScanFormatError` naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rangeret.atomic import atomic_write_bytes

POINT_BYTES = 16
LABEL_BYTES = 4
SCAN_DTYPE = np.dtype("<f4")
LABEL_DTYPE = np.dtype("<u4")


class ScanFormatError(ValueError):
    """A scan or label file (or buffer) that is not valid SemanticKITTI data."""

    def __init__(self, source: str | os.PathLike[str], problem: str) -> None:
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")


def parse_scan(data: bytes | memoryview, source: str = "<scan>") -> np.ndarray:
    """Decode the bytes of a `.bin` scan into a float32 (N, 4) array, validating them."""
    size = len(data)
    if size == 0:
        raise ScanFormatError(source, "the scan is empty (0 bytes)")
    if size % POINT_BYTES:
        raise ScanFormatError(
            source,
            f"size {size} bytes is not a multiple of {POINT_BYTES} "
            f"(4 float32 per point: x, y, z, remission); the file is truncated or not a scan",
        )
    points = np.frombuffer(data, dtype=SCAN_DTYPE).reshape(-1, 4)
    finite = np.isfinite(points)
    if not finite.all():
        rows = np.flatnonzero(~finite.all(axis=1))
        raise ScanFormatError(
            source,
            f"{rows.size} point(s) hold non-finite values (NaN or infinity), "
            f"the first at point index {rows[0]}",
        )
    return points.astype(np.float32, copy=False)


def read_scan(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a `.bin` scan as a float32 (N, 4) array (x, y, z, remission).

    Raises `ScanFormatError` when the file is empty, its size is not a multiple of 16 bytes or it
    holds non-finite values, and `FileNotFoundError` when it does not exist.
    """
    path = Path(path)
    return parse_scan(path.read_bytes(), str(path)).copy()


def scan_num_points(path: str | os.PathLike[str]) -> int:
    """Number of points of a `.bin` scan from its size alone (no read), validating the size."""
    size = os.path.getsize(path)
    if size == 0:
        raise ScanFormatError(path, "the scan is empty (0 bytes)")
    if size % POINT_BYTES:
        raise ScanFormatError(path, f"size {size} bytes is not a multiple of {POINT_BYTES}")
    return size // POINT_BYTES


def read_labels(path: str | os.PathLike[str], num_points: int | None = None) -> np.ndarray:
    """Read a `.label` file as uint32 (N,) (raw id in the low 16 bits, instance in the high 16).

    With `num_points`, a file with another number of labels raises `ScanFormatError`.
    """
    path = Path(path)
    size = path.stat().st_size
    if size % LABEL_BYTES:
        raise ScanFormatError(
            path, f"size {size} bytes is not a multiple of {LABEL_BYTES} (one uint32 per point)"
        )
    if num_points is not None and size // LABEL_BYTES != num_points:
        raise ScanFormatError(
            path, f"holds {size // LABEL_BYTES} labels but the scan has {num_points} points"
        )
    return np.fromfile(path, dtype=LABEL_DTYPE).astype(np.uint32, copy=False)


def write_labels(path: str | os.PathLike[str], labels: np.ndarray) -> None:
    """Write uint32 labels atomically as a `.label` file."""
    labels = np.asarray(labels)
    if labels.ndim != 1:
        raise ValueError(f"{path}: labels must be one-dimensional, got shape {labels.shape}")
    if labels.size and (labels.min() < 0 or labels.max() > np.iinfo(np.uint32).max):
        raise ValueError(f"{path}: labels do not fit in uint32")
    atomic_write_bytes(path, labels.astype(LABEL_DTYPE, copy=False).tobytes())


def write_scan(path: str | os.PathLike[str], points: np.ndarray) -> None:
    """Write float (N, 4) points atomically as a `.bin` scan."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"{path}: points must have shape (N, 4), got {points.shape}")
    atomic_write_bytes(path, points.astype(SCAN_DTYPE, copy=False).tobytes())
