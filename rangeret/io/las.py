"""LAS and LAZ files, read and written with laspy (BSD-2-Clause; LAZ through lazrs, MIT), both in
the `files` extra.

Columns are the scaled coordinates `x`, `y`, `z` (float64, as laspy computes them from the stored
integers, scale and offset) and every other dimension under its own name, extra-bytes ones
included. LAS intensity is a uint16: it is read as a reflectance in 0..1, `intensity / 65535`,
which the reader's notes say (and run.json records). The header's fixed fields are read and
checked here before laspy parses the rest: its size, the offset to the points, the (E)VLRs it
declares (each needs its 54 or 60 bytes in the file, so a forged count cannot have laspy read
a million of them) and the points times the record length, so a file can be refused before
anything is decompressed or allocated. Labelled output adds the extra-bytes dimensions `label`
(uint32) and `confidence` (float32), with panoptic segmentation `instance` (uint32) too.
"""

from __future__ import annotations

import copy
import io
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from rangeret.extras import require_extra
from rangeret.io.decode_limits import Declared
from rangeret.io.scans import ScanFormatError

#: The signature every LAS and LAZ file starts with.
SIGNATURE = b"LASF"
#: How LAS intensity becomes the reflectance a profile's record reads.
INTENSITY_SCALE = 65535.0
INTENSITY_NOTE = "LAS intensity (uint16) read as remission = intensity / 65535"
#: The raw integer coordinates, not columns: their scaled values are.
_RAW_COORDINATES = ("X", "Y", "Z")
#: Bytes of the LAS 1.0-1.2 header, the least any version has, and of the LAS 1.4 one.
MIN_HEADER, HEADER_1_4 = 227, 375
#: Bytes of a VLR's header and of an extended VLR's.
VLR_BYTES, EVLR_BYTES = 54, 60


class LasFormatError(ScanFormatError):
    """A LAS or LAZ file (or body) that cannot be read, naming the source and the problem."""


def is_las(head: bytes) -> bool:
    """Whether bytes start with the LAS signature."""
    return head.startswith(SIGNATURE)


def _laspy() -> Any:
    require_extra("reading LAS/LAZ files", "files")
    import laspy

    return laspy


def _errors(laspy: Any) -> tuple[type[BaseException], ...]:
    """What laspy and lazrs raise for bad input."""
    import lazrs

    return (
        laspy.errors.LaspyException, lazrs.LazrsError, ValueError, OSError, EOFError, KeyError,
        IndexError, TypeError, OverflowError, struct.error,
    )  # fmt: skip


@dataclass(frozen=True)
class LasHeaderInfo:
    """What a LAS header declares: points, whether they are compressed (LAZ), and the layout."""

    points: int
    compressed: bool
    version: str
    point_format: int


@dataclass(frozen=True)
class LasLayout:
    """The fixed fields of a LAS header that bound the rest of the file."""

    minor: int
    header_size: int
    offset: int
    vlrs: int
    point_size: int
    points: int
    evlr_start: int
    evlrs: int


def read_layout(data: bytes | memoryview, source: str, size: int | None = None) -> LasLayout:
    """The fixed fields of a LAS header (from the file's first bytes; `size`: the file's, default
    `len(data)`), checked against the file's size; LasFormatError when they cannot hold."""
    size = len(data) if size is None else size
    head = bytes(data[:HEADER_1_4])
    if not is_las(head):
        raise LasFormatError(source, "is not a LAS file (no LASF signature)")
    minor = head[25] if len(head) > 25 else 0
    need = HEADER_1_4 if minor >= 4 else MIN_HEADER
    if min(len(head), size) < need:
        raise LasFormatError(
            source, f"the LAS 1.{minor} header needs {need} bytes, the file holds {size}"
        )
    header_size, offset, vlrs, _, point_size, points = struct.unpack_from("<HIIBHI", head, 94)
    evlr_start, evlrs = 0, 0
    if minor >= 4:
        evlr_start, evlrs, points = struct.unpack_from("<QIQ", head, 235)
    layout = LasLayout(minor, header_size, offset, vlrs, point_size, points, evlr_start, evlrs)
    _check_layout(layout, size, source)
    return layout


def _check_layout(layout: LasLayout, size: int, source: str) -> None:
    """LasFormatError when the header, its VLRs or its EVLRs cannot fit the file."""
    if not MIN_HEADER <= layout.header_size <= min(layout.offset, size):
        raise LasFormatError(
            source,
            f"the LAS header declares {layout.header_size} header bytes and its points at "
            f"{layout.offset}, in a file of {size} bytes",
        )
    room = layout.offset - layout.header_size
    if layout.offset > size or layout.vlrs * VLR_BYTES > room:
        raise LasFormatError(
            source,
            f"the LAS header declares {layout.vlrs:,} VLRs, but the {room:,} bytes between its "
            f"header and its points (at {layout.offset:,} of {size:,}) hold at most "
            f"{max(room, 0) // VLR_BYTES:,}",
        )
    if layout.evlrs and not (
        layout.offset <= layout.evlr_start and layout.evlr_start + layout.evlrs * EVLR_BYTES <= size
    ):
        raise LasFormatError(
            source,
            f"the LAS header declares {layout.evlrs:,} EVLRs at {layout.evlr_start:,}, which do "
            f"not fit in the file's {size:,} bytes",
        )


def declared(data: bytes | memoryview, source: str, size: int | None = None) -> Declared:
    """The points a LAS/LAZ declares and its point record's bytes, from its header alone."""
    layout = read_layout(data, source, size)
    return Declared(layout.points, layout.point_size)


def read_header(data: bytes | memoryview, source: str) -> LasHeaderInfo:
    """The header of a LAS/LAZ file's bytes, nothing decompressed; LasFormatError when it
    cannot be read."""
    read_layout(data, source)
    laspy = _laspy()
    try:
        with laspy.open(io.BytesIO(data)) as reader:
            header = reader.header
            return LasHeaderInfo(
                points=int(header.point_count),
                compressed=bool(header.are_points_compressed),
                version=str(header.version),
                point_format=int(header.point_format.id),
            )
    except _errors(laspy) as exc:
        raise LasFormatError(source, f"the LAS header cannot be read ({exc})") from exc


def declared_points(data: bytes | memoryview, source: str) -> int:
    """The points a LAS/LAZ declares, from its header alone."""
    return read_layout(data, source).points


@dataclass(frozen=True)
class LasCloud:
    """A decoded LAS/LAZ file: laspy's data (kept for writing back) and its header facts."""

    data: Any
    header: LasHeaderInfo

    def columns(self) -> dict[str, np.ndarray]:
        """Scaled x, y, z, intensity / 65535, then every other dimension by name."""
        las = self.data
        columns = {axis: np.asarray(getattr(las, axis), dtype=np.float64) for axis in "xyz"}
        for name in las.point_format.dimension_names:
            if name in _RAW_COORDINATES:
                continue
            values = np.asarray(las[name])
            if name == "intensity":
                values = (values / INTENSITY_SCALE).astype(np.float32)
            if values.ndim == 1:
                columns[name] = values
        return columns


def read_las(data: bytes | memoryview, source: str) -> LasCloud:
    """Decode a LAS/LAZ file's bytes; LasFormatError when it is truncated or cannot be decoded."""
    info = read_header(data, source)
    laspy = _laspy()
    kind = "LAZ" if info.compressed else "LAS"
    try:
        with laspy.open(io.BytesIO(data)) as reader:
            start = reader.header.offset_to_point_data
            if info.compressed:
                check_chunk_table(data, start, info.points, source)
            need = start + info.points * reader.header.point_format.size
            short = not info.compressed and len(data) < need
            las = None if short else reader.read()
    except LasFormatError:
        raise
    except _errors(laspy) as exc:
        raise LasFormatError(source, f"the {kind} points cannot be decoded ({exc})") from exc
    if las is None:
        raise LasFormatError(
            source,
            f"holds {len(data)} bytes, its {info.points} points need {need} (the file is truncated)",
        )
    if len(las.points) != info.points:
        raise LasFormatError(
            source,
            f"holds {len(las.points)} points, the header declares {info.points} "
            "(the file is truncated)",
        )
    return LasCloud(las, info)


def check_chunk_table(data: bytes | memoryview, start: int, points: int, source: str) -> None:
    """Refuse a LAZ file whose chunk table lies outside it or declares more chunks than it has
    points, before lazrs reads it (a forged chunk count would have it allocate without bound)."""
    size = len(data)
    if size < start + 8:
        raise LasFormatError(source, "the LAZ file ends before its points (it is truncated)")
    (offset,) = struct.unpack("<q", bytes(data[start : start + 8]))
    if offset == -1 and size >= start + 16:  # written last, its offset in the file's last 8 bytes
        (offset,) = struct.unpack("<q", bytes(data[size - 8 :]))
    if not start + 8 <= offset <= size - 8:
        raise LasFormatError(
            source, f"the LAZ chunk table offset {offset} lies outside the file (it is truncated)"
        )
    _, chunks = struct.unpack("<II", bytes(data[offset : offset + 8]))
    if chunks > points + 1:
        raise LasFormatError(
            source, f"the LAZ chunk table declares {chunks} chunks for {points} points"
        )


def labelled_las_bytes(
    cloud: LasCloud,
    labels: np.ndarray,
    confidence: np.ndarray,
    instances: np.ndarray | None = None,
) -> bytes:
    """The file again (LAZ stays compressed) with extra-bytes dimensions `label` (uint32) and
    `confidence` (float32), and given `instances`, `instance` (uint32); a dimension of one of
    those names already there is replaced, so a narrower one cannot cut the values. `cloud`
    itself is not changed."""
    laspy = _laspy()
    las = laspy.LasData(copy.deepcopy(cloud.data.header), cloud.data.points.copy())
    added = {"label": (np.uint32, labels), "confidence": (np.float32, confidence)}
    if instances is not None:
        added["instance"] = (np.uint32, instances)
    present = set(las.point_format.extra_dimension_names)
    replaced = [name for name in added if name in present]
    if replaced:
        las.remove_extra_dims(replaced)
    las.add_extra_dims(
        [laspy.ExtraBytesParams(name=name, type=kind) for name, (kind, _) in added.items()]
    )
    for name, (_, values) in added.items():
        las[name] = values
    out = io.BytesIO()
    backend = laspy.LazBackend.Lazrs if cloud.header.compressed else None
    las.write(out, do_compress=cloud.header.compressed, laz_backend=backend)
    return out.getvalue()
