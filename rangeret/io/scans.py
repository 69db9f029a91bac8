"""Reading and writing scan (`.bin`) and label (`.label`) files, with validation.

A scan is little-endian float32 records, one per point: SemanticKITTI's hold (x, y, z, remission),
16 bytes; other datasets' records are described by a `PointRecord` (PandaSet's add the laser id,
20 bytes). A label file is one little-endian uint32 per point: the low 16 bits are the raw
semantic id, the high 16 bits the instance id. Every reader checks what it reads and raises
`ScanFormatError` naming the file.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from rangeret.exceptions import InputError, InputFileMissing
from rangeret.io.atomic import atomic_path, atomic_write_bytes
from rangeret.io.regular_files import NotRegularFileError, open_regular

POINT_BYTES = 16
LABEL_BYTES = 4
SCAN_DTYPE = np.dtype("<f4")
LABEL_DTYPE = np.dtype("<u4")


@dataclass(frozen=True)
class PointRecord:
    """What one point of a scan file holds: float32 values named by `fields`, in order.

    The first four are always x, y, z and the reflectance (remission or intensity); a fifth, where
    a dataset has one, is kept for the projection (a laser id gives the point's row).
    """

    fields: tuple[str, ...] = ("x", "y", "z", "remission")

    def __post_init__(self) -> None:
        if len(self.fields) not in (4, 5):
            raise ValueError(f"a point record holds 4 or 5 float32 values, got {len(self.fields)}")
        if tuple(self.fields[:3]) != ("x", "y", "z"):
            raise ValueError(
                f"a point record starts with x, y, z, got {', '.join(self.fields[:3])}"
            )
        if len(set(self.fields)) != len(self.fields):
            raise ValueError(f"a point record names each value once, got {', '.join(self.fields)}")

    @property
    def num_fields(self) -> int:
        """float32 values per point."""
        return len(self.fields)

    @property
    def point_bytes(self) -> int:
        """Bytes per point."""
        return 4 * len(self.fields)

    def describe(self) -> str:
        """'4 float32 per point: x, y, z, remission', for messages."""
        return f"{self.num_fields} float32 per point: {', '.join(self.fields)}"


#: SemanticKITTI's point record (x, y, z, remission).
KITTI_RECORD = PointRecord()


class ScanFormatError(InputError, ValueError):
    """A scan or label file (or buffer) that is not valid SemanticKITTI data."""

    def __init__(self, source: str | os.PathLike[str], problem: str) -> None:
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")


def parse_scan(
    data: bytes | memoryview | np.ndarray, source: str = "<scan>", *, record: PointRecord
) -> np.ndarray:
    """Decode the bytes of a `.bin` scan (or a uint8 array holding them) into a float32
    (N, fields) array, validating them; a view of `data` where it can be."""
    size = len(data)
    if size == 0:
        raise ScanFormatError(source, "the scan is empty (0 bytes)")
    if size % record.point_bytes:
        raise ScanFormatError(
            source,
            f"size {size} bytes is not a multiple of {record.point_bytes} "
            f"({record.describe()}); the file is truncated or not a scan of this dataset",
        )
    points = np.frombuffer(data, dtype=SCAN_DTYPE).reshape(-1, record.num_fields)
    # min and max are NaN where any value is, and infinite where one is: two passes, no copy
    if not (np.isfinite(points.min()) and np.isfinite(points.max())):
        rows = np.flatnonzero(~np.isfinite(points).all(axis=1))
        raise ScanFormatError(
            source,
            f"{rows.size} point(s) hold non-finite values (NaN or infinity), "
            f"the first at point index {rows[0]}",
        )
    return points.astype(np.float32, copy=False)


def read_scan(
    path: str | os.PathLike[str],
    record: PointRecord = KITTI_RECORD,
    within: Sequence[str | os.PathLike[str]] | None = None,
) -> np.ndarray:
    """Read a `.bin` scan as a float32 (N, fields) array ((N, 4) x, y, z, remission by default:
    the one-argument form is a public contract; the project's own code always passes `record`).

    Raises `ScanFormatError` when the file is empty, its size is not a whole number of records or
    it holds non-finite values, and `FileNotFoundError` when it does not exist. With `within`,
    the file opened must lie under one of those folders once links are resolved (judged on the
    open file itself, so a link swapped in meanwhile is caught): else `ScanFormatError`.
    """
    path = Path(path)
    try:
        with open_regular(path, "a scan") as f:
            if within is not None:
                _check_within(f.fileno(), path, within)
            data = _read_all(f)
    except NotRegularFileError as exc:
        raise ScanFormatError(path, f"it is {exc.kind}, not a scan file") from None
    return parse_scan(data, str(path), record=record)


def _read_all(f: BinaryIO) -> np.ndarray:
    """The whole of a regular file just opened, as a new uint8 array read into in one go (no
    bytes object to copy from)."""
    info = os.fstat(f.fileno())
    data = np.empty(info.st_size + 1, dtype=np.uint8)
    got = f.readinto(data)
    if got <= info.st_size:
        return data[:got]
    return np.concatenate([data[:got], np.frombuffer(f.read(), dtype=np.uint8)])


def _check_within(fd: int, path: Path, within: Sequence[str | os.PathLike[str]]) -> None:
    """`ScanFormatError` unless the file open as `fd` lies under one of the folders `within`,
    judged on the open file itself."""
    opened = _opened_path(fd, path)
    roots = [os.path.realpath(r) for r in within]
    if not any(opened == r or opened.startswith(r.rstrip(os.sep) + os.sep) for r in roots):
        raise ScanFormatError(path, "it leads outside the folders this run may read")


def _opened_path(fd: int, path: Path) -> str:
    """The real path of the file open as `fd` (from /proc where there is one)."""
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError:
        return os.path.realpath(path)


def scan_num_points(path: str | os.PathLike[str], *, record: PointRecord) -> int:
    """Number of points of a `.bin` scan from its size alone (no read), validating the size."""
    size = os.path.getsize(path)
    if size == 0:
        raise ScanFormatError(path, "the scan is empty (0 bytes)")
    if size % record.point_bytes:
        raise ScanFormatError(
            path,
            f"size {size} bytes is not a multiple of {record.point_bytes} ({record.describe()})",
        )
    return size // record.point_bytes


@dataclass(frozen=True)
class LabelFile:
    """How a dataset's label and prediction files hold one label per point: little-endian
    unsigned integers of `bytes` each (SemanticKITTI's `.label`: 4, raw id in the low 16 bits and
    the instance above; nuScenes-lidarseg's `_lidarseg.bin`: 1, a class index)."""

    bytes: int = 4

    def __post_init__(self) -> None:
        if self.bytes not in (1, 2, 4):
            raise ValueError(f"a label is 1, 2 or 4 bytes, got {self.bytes}")

    @property
    def dtype(self) -> np.dtype:
        """The numpy dtype of one label."""
        return np.dtype(f"<u{self.bytes}")

    def count(self, path: str | os.PathLike[str]) -> int:
        """Labels in a file, from its size alone; `ScanFormatError` for a partial label."""
        path = Path(path)
        try:
            size = path.stat().st_size
        except FileNotFoundError as exc:
            raise InputFileMissing.of(exc) from exc
        if size % self.bytes:
            raise ScanFormatError(
                path,
                f"size {size} bytes is not a multiple of {self.bytes} "
                f"(one uint{8 * self.bytes} per point)",
            )
        return size // self.bytes

    def holds(self, path: str | os.PathLike[str], num_points: int) -> bool:
        """Whether the file holds exactly `num_points` labels (its size says so)."""
        try:
            return Path(path).stat().st_size == num_points * self.bytes
        except OSError:
            return False

    def read(self, path: str | os.PathLike[str], num_points: int | None = None) -> np.ndarray:
        """The file's labels as uint32 (N,); with `num_points`, another count raises
        `ScanFormatError`."""
        count = self.count(path)
        if num_points is not None and count != num_points:
            raise ScanFormatError(
                path, f"holds {count} labels but the scan has {num_points} points"
            )
        return np.fromfile(path, dtype=self.dtype).astype(np.uint32, copy=False)

    def write(self, path: str | os.PathLike[str], labels: np.ndarray) -> None:
        """Write labels atomically, each in `bytes` bytes (a value that does not fit is a
        ValueError naming the file)."""
        labels = np.asarray(labels)
        if labels.ndim != 1:
            raise ValueError(f"{path}: labels must be one-dimensional, got shape {labels.shape}")
        if labels.size and (labels.min() < 0 or labels.max() > np.iinfo(self.dtype).max):
            raise ValueError(f"{path}: labels do not fit in uint{self.bytes * 8}")
        atomic_write_bytes(path, _bytes_of(labels.astype(self.dtype, copy=False)))


#: SemanticKITTI's `.label` files: one uint32 per point.
KITTI_LABELS = LabelFile(LABEL_BYTES)


def read_labels(path: str | os.PathLike[str], num_points: int | None = None) -> np.ndarray:
    """Read a `.label` file as uint32 (N,) (raw id in the low 16 bits, instance in the high 16).

    With `num_points`, a file with another number of labels raises `ScanFormatError`.
    """
    return KITTI_LABELS.read(path, num_points)


def write_labels(path: str | os.PathLike[str], labels: np.ndarray) -> None:
    """Write uint32 labels atomically as a `.label` file."""
    KITTI_LABELS.write(path, labels)


def write_confidence(path: str | os.PathLike[str], confidence: np.ndarray) -> None:
    """Write per-point confidences (0..1) atomically as a float16 `.npy` file."""
    confidence = np.asarray(confidence)
    if confidence.ndim != 1:
        raise ValueError(f"{path}: confidences must be one-dimensional, got {confidence.shape}")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, confidence.astype(np.float16))


def read_confidence(path: str | os.PathLike[str], num_points: int | None = None) -> np.ndarray:
    """Per-point confidences of a `.npy` file as float32; ScanFormatError for another count."""
    try:
        values = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ScanFormatError(path, f"is not a confidence file ({exc})") from exc
    if values.ndim != 1 or (num_points is not None and values.size != num_points):
        raise ScanFormatError(
            path, f"holds {values.size} confidences but the scan has {num_points} points"
        )
    return values.astype(np.float32)


def write_scan(path: str | os.PathLike[str], points: np.ndarray, *, record: PointRecord) -> None:
    """Write float (N, fields) points atomically as a `.bin` scan."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != record.num_fields:
        raise ValueError(
            f"{path}: points must have shape (N, {record.num_fields}), got {points.shape}"
        )
    atomic_write_bytes(path, _bytes_of(points.astype(SCAN_DTYPE, copy=False)))


def _bytes_of(values: np.ndarray) -> memoryview:
    """The bytes of an array, without a copy when it is contiguous."""
    return memoryview(np.ascontiguousarray(values)).cast("B")
