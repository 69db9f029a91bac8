"""Panoptic labels: how one value per point packs its semantic label and its object, and the
nuScenes-panoptic `.npz` file that holds them.

Two encodings, each a benchmark's definition:

- `SHIFTED` (SemanticKITTI panoptic): `instance << 16 | semantic`, in a `.label` file of uint32;
  the low 16 bits are exactly the semantic label a plain prediction holds. Instances are the
  scan's own ids (at most 65,535).
- `THOUSANDS` (nuScenes-panoptic): `1000 * class + instance`, uint16 in an `.npz` of one array
  `data`; instances are numbered 1, 2, ... within each class, so a scan holds at most 999 objects
  of one class. A scan with more is refused (its prediction fails, naming the class), never
  wrapped into another class's values.

Stuff points have instance 0 in both.
"""

from __future__ import annotations

import io
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangeret.exceptions import InputError, InputFileMissing
from rangeret.io.atomic import atomic_path
from rangeret.io.scans import ScanFormatError
from rangeret.io.zipfiles import ReproducibleZip


class PanopticEncodingError(InputError, ValueError):
    """A scan's objects that its benchmark's panoptic label cannot hold."""


@dataclass(frozen=True)
class PanopticEncoding:
    """One benchmark's packing of (semantic value, instance) into one label per point."""

    name: str
    #: semantic * multiplier + instance (THOUSANDS), or instance * multiplier + semantic (SHIFTED).
    multiplier: int
    #: Whether the instance is the high part (SHIFTED) rather than the low one (THOUSANDS).
    instance_high: bool
    #: The largest instance id one label holds (per class where instances restart per class).
    max_instance: int
    #: Instances are renumbered 1, 2, ... within each class.
    per_class: bool

    def encode(
        self, semantic: np.ndarray, instances: np.ndarray, classes: np.ndarray
    ) -> np.ndarray:
        """uint32 labels of points with `semantic` values (what a plain prediction holds) and
        scan-unique `instances` (0 for stuff); `classes` are the points' training classes,
        which name a class in a refusal."""
        semantic = np.asarray(semantic, dtype=np.uint32)
        instances = np.asarray(instances, dtype=np.uint32)
        if self.per_class:
            instances = _per_class(instances, classes)
        over = instances > self.max_instance
        if over.any():
            cls = int(np.asarray(classes)[np.argmax(over)])
            count = int(instances[np.asarray(classes) == cls].max())
            raise PanopticEncodingError(
                f"the scan has {count} objects of class {cls}; a {self.name} label holds at most "
                f"{self.max_instance}{' per class' if self.per_class else ''}"
            )
        if self.instance_high:
            return instances * np.uint32(self.multiplier) + semantic
        if semantic.size and int(semantic.max()) > (1 << 16) // self.multiplier - 1:
            raise PanopticEncodingError(
                f"semantic value {int(semantic.max())} does not fit a {self.name} label"
            )
        return semantic * np.uint32(self.multiplier) + instances

    def semantic(self, labels: np.ndarray) -> np.ndarray:
        """The semantic part of each label (uint32)."""
        labels = np.asarray(labels, dtype=np.uint32)
        if self.instance_high:
            return labels % np.uint32(self.multiplier)
        return labels // np.uint32(self.multiplier)

    def instance(self, labels: np.ndarray) -> np.ndarray:
        """The instance part of each label (uint32; per class for THOUSANDS)."""
        labels = np.asarray(labels, dtype=np.uint32)
        if self.instance_high:
            return labels // np.uint32(self.multiplier)
        return labels % np.uint32(self.multiplier)


def _per_class(instances: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """Scan-unique instance ids renumbered 1, 2, ... within each class, in id order."""
    out = np.zeros_like(instances)
    things = instances > 0
    if not things.any():
        return out
    classes = np.asarray(classes, dtype=np.int64)
    ids, inverse = np.unique(instances[things], return_inverse=True)
    id_class = np.zeros(ids.size, dtype=np.int64)
    id_class[inverse] = classes[things]
    order = np.lexsort((ids, id_class))
    sorted_class = id_class[order]
    starts = np.r_[0, np.flatnonzero(np.diff(sorted_class)) + 1]
    rank = np.arange(ids.size) - np.repeat(starts, np.diff(np.r_[starts, ids.size]))
    number = np.empty(ids.size, dtype=np.uint32)
    number[order] = rank + 1
    out[things] = number[inverse]
    return out


SHIFTED = PanopticEncoding(
    "SemanticKITTI panoptic", 1 << 16, instance_high=True, max_instance=0xFFFF, per_class=False
)
THOUSANDS = PanopticEncoding(
    "nuScenes-panoptic", 1000, instance_high=False, max_instance=999, per_class=True
)

#: The member of a nuScenes-panoptic `.npz` that holds its one array, `data`.
NPZ_MEMBER = "data.npy"
#: The dtype of a panoptic file's values (the devkit writes native uint16, little-endian).
NPZ_DTYPE = np.dtype("<u2")
#: Bytes a panoptic file may hold beyond its values (the zip's records, the array's header).
NPZ_OVERHEAD_BYTES = 64 << 10
#: The most values a panoptic file may declare when no point count is known to check it with
#: (ten times the largest sweeps').
MAX_NPZ_VALUES = 10_000_000
#: How much of the array's start holds its header, at most.
_NPY_HEAD_BYTES = 16 << 10


def write_panoptic_npz(path: str | os.PathLike[str], values: np.ndarray) -> None:
    """Write a panoptic file atomically: the npz the devkit reads (one array `data`, uint16 per
    point), deflated and reproducible (the same values give the same bytes); a value that does
    not fit in uint16 is a ValueError naming the file."""
    values = np.asarray(values)
    if values.ndim != 1:
        raise ValueError(f"{path}: panoptic values must be one-dimensional, got {values.shape}")
    if values.size and (values.min() < 0 or values.max() > np.iinfo(NPZ_DTYPE).max):
        raise ValueError(f"{path}: panoptic values do not fit in uint16")
    array = io.BytesIO()
    np.lib.format.write_array(array, values.astype(NPZ_DTYPE), allow_pickle=False)
    with atomic_path(path) as tmp, ReproducibleZip(tmp) as zf:
        zf.add_file(NPZ_MEMBER, array.getvalue())


def read_panoptic_npz(
    path: str | os.PathLike[str], num_points: int | None = None, data: bytes | None = None
) -> np.ndarray:
    """A panoptic file's values as uint16: one per point of a sweep of `num_points` points (None:
    as many as it declares, at most `MAX_NPZ_VALUES`), read from `path` or from its bytes `data`
    (`path` then only names it). `ScanFormatError` naming the file for a file that is no npz,
    holds no array `data`, or holds another dtype, shape or number of values. No pickle is
    loaded, and no more is read or inflated than the values and a bounded header take."""
    path = Path(path)
    if data is None:
        try:
            size = path.stat().st_size
        except FileNotFoundError as exc:
            raise InputFileMissing.of(exc) from exc
        if path.is_dir():
            raise ScanFormatError(path, "is a folder, not a panoptic npz file")
    else:
        size = len(data)
    most = MAX_NPZ_VALUES if num_points is None else num_points
    if size > most * NPZ_DTYPE.itemsize + NPZ_OVERHEAD_BYTES:
        raise ScanFormatError(
            path,
            f"is {size:,} bytes, more than a panoptic file of {most:,} points takes "
            f"({most * NPZ_DTYPE.itemsize:,} bytes of uint16 values and at most "
            f"{NPZ_OVERHEAD_BYTES:,} more)",
        )
    try:
        with zipfile.ZipFile(path if data is None else io.BytesIO(data)) as zf:
            names = zf.namelist()
            member = next((n for n in (NPZ_MEMBER, "data") if n in names), None)
            if member is None:
                held = ", ".join(n.removesuffix(".npy") for n in names[:5]) or "nothing"
                raise ScanFormatError(path, f"holds no array 'data' (it holds {held})")
            with zf.open(member) as f:
                head = f.read(_NPY_HEAD_BYTES)
                dtype, shape, offset = _npy_header(head)
                _check_panoptic_array(path, dtype, shape, num_points)
                expected = shape[0] * NPZ_DTYPE.itemsize
                values = head[offset : offset + expected]
                values += f.read(expected - len(values))
    except ScanFormatError:
        raise
    except (
        zipfile.BadZipFile,
        OSError,
        EOFError,
        RuntimeError,
        NotImplementedError,
        ValueError,
    ) as exc:
        raise ScanFormatError(path, f"is not a panoptic npz file ({exc})") from exc
    if len(values) != expected:
        raise ScanFormatError(
            path, f"ends after {len(values):,} of the {expected:,} bytes its header declares"
        )
    return np.frombuffer(values, dtype=dtype).astype(np.uint16)


def _npy_header(head: bytes) -> tuple[np.dtype, tuple[int, ...], int]:
    """The dtype, shape and data offset of the `.npy` array that `head` starts; ValueError for
    another format or a header longer than `head`."""
    buf = io.BytesIO(head)
    version = np.lib.format.read_magic(buf)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(buf)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(buf)
    else:
        raise ValueError(f"npy format version {version[0]}.{version[1]} is not read")
    return dtype, shape, buf.tell()


def _check_panoptic_array(
    path: Path, dtype: np.dtype, shape: tuple[int, ...], points: int | None
) -> None:
    """`ScanFormatError` unless the array is one uint16 per point of the sweep (of at most
    `MAX_NPZ_VALUES` where the sweep's points are not known)."""
    if dtype.kind != "u" or dtype.itemsize != 2:
        raise ScanFormatError(path, f"holds {dtype} values in 'data', not uint16")
    if len(shape) != 1:
        raise ScanFormatError(
            path, f"holds an array 'data' of shape {shape}, not one value per point"
        )
    if points is None and shape[0] > MAX_NPZ_VALUES:
        raise ScanFormatError(
            path, f"declares {shape[0]:,} panoptic values, more than any sweep holds"
        )
    if points is not None and shape[0] != points:
        raise ScanFormatError(
            path, f"holds {shape[0]:,} panoptic values but the sweep has {points:,} points"
        )


@dataclass(frozen=True)
class NpzLabelFile:
    """nuScenes-panoptic's label and prediction files: an `.npz` holding one uint16 array `data`,
    one label per point. Answers as `LabelFile` does (read, write, count, holds)."""

    bytes: int = 2

    @property
    def dtype(self) -> np.dtype:
        """The numpy dtype of one label."""
        return NPZ_DTYPE

    def read(self, path: str | os.PathLike[str], num_points: int | None = None) -> np.ndarray:
        """The file's labels as uint32 (N,); a file that is not such an `.npz`, or (with
        `num_points`) holds another count, is a `ScanFormatError` naming it."""
        return read_panoptic_npz(path, num_points).astype(np.uint32)

    def parse(self, data: bytes, source: str, num_points: int | None = None) -> np.ndarray:
        """The labels of an `.npz` file's bytes (named `source` in errors), as `read` gives
        them."""
        return read_panoptic_npz(source, num_points, data).astype(np.uint32)

    def count(self, path: str | os.PathLike[str]) -> int:
        """Labels in the file."""
        return int(self.read(path).size)

    def holds(self, path: str | os.PathLike[str], num_points: int) -> bool:
        """Whether the file is a complete panoptic file of `num_points` labels."""
        try:
            read_panoptic_npz(path, num_points)
        except (OSError, ScanFormatError):
            return False
        return True

    def write(self, path: str | os.PathLike[str], labels: np.ndarray) -> None:
        """Write labels atomically as a reproducible `.npz` of one uint16 array `data`."""
        write_panoptic_npz(path, labels)


#: nuScenes-panoptic's `_panoptic.npz` files.
PANOPTIC_NPZ = NpzLabelFile()
