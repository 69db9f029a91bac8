"""Point-cloud files of any supported format as named columns, and their labelled copies.

The format comes from the extension (`.pcd`, `.ply`, `.las`, `.laz`, `.bin`), else from the
file's first bytes (`# .PCD`, `VERSION` or `FIELDS` for PCD, `ply` for PLY, `LASF` for LAS/LAZ);
anything else whose size is a whole number of the profile's point records is a `.bin` scan. A file
reads as `{field name: 1-D array}` in the file's point order plus notes on how values were
converted (LAS intensity's scaling), which `rangeret.io.point_fields.to_record` turns into the
profile's record. Before anything is decoded, the header's declared points and point size are
checked against `DecodeLimits` (`rangeret.io.decode_limits`): what would decode past them is a
`DecodeLimitError`, and a file read from disk is read whole only once its header passed. A
malformed or truncated file is a `ScanFormatError` naming it and the problem. PCD and LAS/LAZ
need the `files` extra; PLY and `.bin` do not.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rangeret.exceptions import InputFileMissing
from rangeret.io import las, pcd, ply
from rangeret.io.atomic import atomic_write_bytes
from rangeret.io.decode_limits import DEFAULT_LIMITS, Declared, DecodeLimits
from rangeret.io.scans import PointRecord, ScanFormatError, parse_scan

#: File extensions and the format each names (`.laz` is LAS whose points are compressed).
EXTENSIONS = {".pcd": "pcd", ".ply": "ply", ".las": "las", ".laz": "las", ".bin": "bin"}
#: The formats read, as `PointFile.format` names them.
FORMATS = ("pcd", "ply", "las", "laz", "bin")
#: Bytes of a file read to judge its header (PCD and PLY headers must end within them).
HEAD_BYTES = 64 << 10


class PointFileError(ScanFormatError):
    """A file whose format cannot be told, or that cannot be written back in its format."""


@dataclass(frozen=True)
class PointFile:
    """One decoded point-cloud file: its columns in point order, and what it was."""

    source: str
    #: pcd, ply, las, laz or bin.
    format: str
    #: PCD: ascii, binary, binary_compressed; PLY: ascii, binary_little_endian,
    #: binary_big_endian; LAS/LAZ: the LAS version and point format; bin: the record.
    encoding: str
    columns: dict[str, np.ndarray]
    notes: tuple[str, ...] = ()
    #: The format's decoded form, kept to write the file back with labels.
    decoded: Any = field(default=None, repr=False)

    @property
    def num_points(self) -> int:
        """Points of the file."""
        return len(next(iter(self.columns.values()))) if self.columns else 0

    @property
    def extension(self) -> str:
        """The extension of a file in this format (`.laz` for compressed LAS)."""
        return f".{self.format}"

    @property
    def can_write_labelled(self) -> bool:
        """Whether the format has room for added fields (a `.bin` record has none)."""
        return self.format != "bin"

    def describe(self) -> dict[str, Any]:
        """Format, encoding, points, fields and notes, for run records."""
        return {
            "format": self.format,
            "encoding": self.encoding,
            "points": self.num_points,
            "file_fields": list(self.columns),
            "notes": list(self.notes),
        }


def signature_format(head: bytes) -> str | None:
    """`pcd`, `ply` or `las` when bytes start with that format's signature, else None."""
    if pcd.is_pcd(head):
        return "pcd"
    if ply.is_ply(head):
        return "ply"
    return "las" if las.is_las(head) else None


def sniff_format(head: bytes, size: int, *, record: PointRecord, source: str) -> str:
    """The format of bytes from their signature (`bin` for a whole number of `record`s);
    PointFileError when it is none of them."""
    signed = signature_format(head)
    if signed is not None:
        return signed
    if size and size % record.point_bytes == 0:
        return "bin"
    raise PointFileError(
        source,
        "is not a PCD, PLY or LAS/LAZ file (no signature) nor a .bin scan "
        f"({size} bytes is not a multiple of {record.point_bytes}: {record.describe()})",
    )


def format_of(name: str | os.PathLike[str], head: bytes, size: int, *, record: PointRecord) -> str:
    """The format of a file: its extension's, else its signature's (see `sniff_format`)."""
    known = EXTENSIONS.get(Path(name).suffix.lower())
    return known or sniff_format(head, size, record=record, source=str(name))


def declare(
    head: bytes | memoryview, fmt: str, *, record: PointRecord, source: str, size: int | None = None
) -> Declared:
    """The points a file says it holds and the bytes of each, from its header alone (`head`:
    its first bytes; `size`: the file's, default `len(head)`; a `.bin`: its size), so that a
    caller can refuse it before decoding or decompressing anything."""
    size = len(head) if size is None else size
    if fmt == "pcd":
        return pcd.declared(head, source)
    if fmt == "ply":
        return ply.declared(head, source)
    if fmt in ("las", "laz"):
        return las.declared(head, source, size)
    if fmt == "bin":
        return Declared(size // record.point_bytes, record.point_bytes)
    raise PointFileError(source, f"format {fmt!r} is not one of {', '.join(FORMATS)}")


def declared_points(data: bytes | memoryview, fmt: str, *, record: PointRecord, source: str) -> int:
    """The points a file says it holds, from its header alone (a `.bin`: its size)."""
    return declare(data, fmt, record=record, source=source).points


def read_point_file(
    path: str | os.PathLike[str],
    *,
    record: PointRecord,
    fmt: str | None = None,
    limits: DecodeLimits = DEFAULT_LIMITS,
) -> PointFile:
    """Read a point-cloud file (format from `fmt`, else its extension, else its signature): its
    header first, checked against `limits`, then the whole file."""
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            head = f.read(HEAD_BYTES)
            fmt = fmt or format_of(path, head[:16], size, record=record)
            found = declare(head, fmt, record=record, source=str(path), size=size)
            limits.check(found, record=record, source=str(path))
            del head
            f.seek(0)
            data = f.read()
    except FileNotFoundError as exc:
        raise InputFileMissing.of(exc) from exc
    except IsADirectoryError as exc:
        raise PointFileError(path, "is a folder, not a point-cloud file") from exc
    return decode_point_file(data, fmt, record=record, source=str(path), limits=limits)


def decode_point_file(
    data: bytes | memoryview,
    fmt: str,
    *,
    record: PointRecord,
    source: str,
    limits: DecodeLimits = DEFAULT_LIMITS,
) -> PointFile:
    """Decode a file's bytes in format `fmt` (pcd, ply, las, laz or bin; las and laz alike),
    its header checked against `limits` first (`DecodeLimitError` past them)."""
    limits.check(declare(data, fmt, record=record, source=source), record=record, source=source)
    if fmt == "pcd":
        cloud = pcd.read_pcd(data, source)
        notes = (f"{cloud.padding} padding field(s) '_' skipped",) if cloud.padding else ()
        return PointFile(source, "pcd", cloud.header.encoding, cloud.columns(), notes, cloud)
    if fmt == "ply":
        cloud = ply.read_ply_cloud(data, source)
        return PointFile(source, "ply", cloud.header.format, cloud.columns(), (), cloud)
    if fmt in ("las", "laz"):
        cloud = las.read_las(data, source)
        info = cloud.header
        columns = cloud.columns()
        notes = (las.INTENSITY_NOTE,) if "intensity" in columns else ()
        encoding = f"LAS {info.version} point format {info.point_format}"
        kind = "laz" if info.compressed else "las"
        return PointFile(source, kind, encoding, columns, notes, cloud)
    points = parse_scan(data, source, record=record)
    columns = {name: points[:, i] for i, name in enumerate(record.fields)}
    return PointFile(source, "bin", record.describe(), columns)


def labelled_bytes(
    point_file: PointFile,
    labels: np.ndarray,
    confidence: np.ndarray,
    instances: np.ndarray | None = None,
) -> bytes:
    """The file again in its own format and encoding, with `label` (uint32 raw ids) and
    `confidence` (float32) per point added, and given `instances` (panoptic segmentation's
    objects, 0 for stuff), `instance` (uint32)."""
    labels = np.asarray(labels, dtype=np.uint32)
    confidence = np.asarray(confidence, dtype=np.float32)
    if instances is not None:
        instances = np.asarray(instances, dtype=np.uint32)
    counts = [len(labels), len(confidence)] + ([] if instances is None else [len(instances)])
    if any(count != point_file.num_points for count in counts):
        given = f"{len(labels)} labels and {len(confidence)} confidences"
        if instances is not None:
            given = f"{len(labels)} labels, {len(confidence)} confidences and {len(instances)} "
            given += "instances"
        raise ValueError(f"{point_file.source}: {given} for {point_file.num_points} points")
    if point_file.format == "pcd":
        return pcd.labelled_pcd_bytes(point_file.decoded, labels, confidence, instances)
    if point_file.format == "ply":
        return ply.labelled_ply_bytes(point_file.decoded, labels, confidence, instances)
    if point_file.format in ("las", "laz"):
        return las.labelled_las_bytes(point_file.decoded, labels, confidence, instances)
    raise PointFileError(
        point_file.source,
        "a .bin scan has no room for added fields (its .label file is the labels)",
    )


def write_labelled(
    path: str | os.PathLike[str],
    point_file: PointFile,
    labels: np.ndarray,
    confidence: np.ndarray,
    instances: np.ndarray | None = None,
) -> Path:
    """Write `labelled_bytes` atomically to `path`."""
    atomic_write_bytes(path, labelled_bytes(point_file, labels, confidence, instances))
    return Path(path)
