"""PLY point clouds: the project's coloured, labelled output, and a reader and labelled writer for
any PLY whose first element is `vertex`.

The writer of `rangeret view` gives one vertex per point with `x`, `y`, `z` (float32), `red`,
`green`, `blue` (uchar) and `label` (uint32, the raw semantic id), under the standard header that
CloudCompare, MeshLab and Open3D read. The reader takes the `ascii`, `binary_little_endian` and
`binary_big_endian` formats; the first element must be `vertex` with scalar properties (a list
property there is an error naming it), and later elements (faces, ...) are skipped. The labelled
writer keeps every vertex property, adds `label` (uint) and `confidence` (float), with panoptic
segmentation `instance` (uint) too, and keeps the file's format; later elements are not written
back.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangeret.io.ascii_points import read_ascii_rows
from rangeret.io.atomic import atomic_write_bytes
from rangeret.io.decode_limits import Declared
from rangeret.io.scans import ScanFormatError

#: The vertex record written: position, colour and raw label.
VERTEX_DTYPE = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("label", "<u4"),
    ]
)

#: PLY scalar type names (both spellings of the format) and their little-endian numpy types.
PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}  # fmt: skip
_TYPE_NAMES = {"<f4": "float", "u1": "uchar", "<u4": "uint"}


class PlyFormatError(ScanFormatError):
    """A PLY file this reader cannot read, naming the file and the problem."""


def ply_bytes(
    xyz: np.ndarray, rgb: np.ndarray, labels: np.ndarray, comments: tuple[str, ...] = ()
) -> bytes:
    """The PLY file of (N, 3) positions, (N, 3) uint8 RGB colours and (N,) raw labels."""
    xyz, rgb, labels = np.asarray(xyz), np.asarray(rgb), np.asarray(labels)
    n = len(xyz)
    if xyz.shape != (n, 3) or rgb.shape != (n, 3) or labels.shape != (n,):
        raise ValueError(
            f"a PLY cloud needs (N, 3) positions, (N, 3) colours and (N,) labels, got "
            f"{xyz.shape}, {rgb.shape} and {labels.shape}"
        )
    vertices = np.empty(n, dtype=VERTEX_DTYPE)
    for i, axis in enumerate("xyz"):
        vertices[axis] = xyz[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        vertices[channel] = rgb[:, i]
    vertices["label"] = labels
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {' '.join(c.split())}" for c in comments]
    header.append(f"element vertex {n}")
    header += [
        f"property {_TYPE_NAMES[VERTEX_DTYPE[name].str.lstrip('|')]} {name}"
        for name in VERTEX_DTYPE.names
    ]
    header.append("end_header")
    return ("\n".join(header) + "\n").encode("ascii") + vertices.tobytes()


def write_ply(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    rgb: np.ndarray,
    labels: np.ndarray,
    comments: tuple[str, ...] = (),
) -> Path:
    """Write a coloured, labelled point cloud atomically as a binary little-endian PLY."""
    atomic_write_bytes(path, ply_bytes(xyz, rgb, labels, comments))
    return Path(path)


#: The formats of a PLY body, and the byte order of the binary ones.
FORMATS = {"ascii": "<", "binary_little_endian": "<", "binary_big_endian": ">"}
#: printf formats of ASCII values that read back exact (integers: %d).
_ASCII_FORMATS = {"float": "%.9g", "float32": "%.9g", "double": "%.17g", "float64": "%.17g"}
#: Bytes of a header read before it must have ended.
HEADER_LIMIT = 64 << 10


@dataclass(frozen=True)
class PlyHeader:
    """What a PLY header declares about its first element, `vertex`."""

    format: str
    count: int
    #: (name, PLY type name) of each vertex property, in order.
    properties: tuple[tuple[str, str], ...]
    #: `comment` and `obj_info` lines, kept for a labelled copy.
    comments: tuple[str, ...]
    data_offset: int

    @property
    def dtype(self) -> np.dtype:
        """One vertex as a numpy record in the file's byte order."""
        order = FORMATS[self.format]
        return np.dtype(
            [
                (name, np.dtype(PLY_TYPES[kind]).newbyteorder(order))
                for name, kind in self.properties
            ]
        )


def is_ply(head: bytes) -> bool:
    """Whether bytes start with the PLY magic line."""
    return head.startswith((b"ply\n", b"ply\r\n"))


def parse_header(data: bytes | memoryview, source: str | os.PathLike[str]) -> PlyHeader:
    """The header of a PLY file's bytes (only the header is read); PlyFormatError when it is not
    a PLY, its first element is not `vertex`, or a vertex property is a list."""
    head = bytes(data[:HEADER_LIMIT])
    end = head.find(b"end_header")
    if not is_ply(head) or end < 0:
        raise PlyFormatError(source, "is not a PLY file (no 'ply' magic or no end_header)")
    newline = head.find(b"\n", end)
    offset = newline + 1 if newline >= 0 else len(head)
    try:
        lines = head[:offset].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise PlyFormatError(source, "the PLY header is not ASCII text") from None
    fmt, count, properties, comments, element = None, None, [], [], None
    for line in lines[1:]:
        words = line.split()
        if not words:
            continue
        key = words[0]
        if key == "format":
            fmt = words[1] if len(words) > 1 else ""
        elif key in ("comment", "obj_info"):
            comments.append(line.strip())
        elif key == "element":
            element = words[1] if len(words) > 1 else ""
            if count is not None:
                break  # only the vertex element, which comes first, is read
            if element != "vertex" or len(words) != 3 or not words[2].isdigit():
                raise PlyFormatError(source, f"the first element is {line.strip()!r}, not vertex N")
            count = int(words[2])
        elif key == "property" and element == "vertex":
            if len(words) > 1 and words[1] == "list":
                name = words[-1] if len(words) > 2 else "?"
                raise PlyFormatError(source, f"vertex property {name!r} is a list, not a scalar")
            if len(words) != 3 or words[1] not in PLY_TYPES:
                raise PlyFormatError(source, f"{line.strip()!r} is not a scalar PLY property")
            properties.append((words[2], words[1]))
    if fmt not in FORMATS:
        raise PlyFormatError(source, f"format {fmt!r} is not one of {', '.join(FORMATS)}")
    if count is None:
        raise PlyFormatError(source, "has no vertex element")
    if len({name for name, _ in properties}) != len(properties):
        raise PlyFormatError(source, "names a vertex property twice")
    return PlyHeader(fmt, count, tuple(properties), tuple(comments), offset)


def declared(data: bytes | memoryview, source: str) -> Declared:
    """The vertices a PLY declares and the bytes of each, from its header alone."""
    header = parse_header(data, source)
    return Declared(header.count, header.dtype.itemsize)


def declared_points(data: bytes | memoryview, source: str) -> int:
    """The vertices a PLY declares, from its header alone."""
    return parse_header(data, source).count


@dataclass(frozen=True)
class PlyCloud:
    """A decoded PLY: its header and its vertices as one structured array (native byte order)."""

    header: PlyHeader
    array: np.ndarray

    def columns(self) -> dict[str, np.ndarray]:
        """Each vertex property as a 1-D array."""
        return {name: self.array[name] for name in self.array.dtype.names or ()}


def read_ply_cloud(data: bytes | memoryview, source: str | os.PathLike[str]) -> PlyCloud:
    """Decode the vertices of a PLY file's bytes into one array (read in place where the file's
    byte order is the machine's); PlyFormatError when they are truncated. The caller bounds the
    declared size (`declared`) first."""
    header = parse_header(data, source)
    dtype = header.dtype
    native = dtype.newbyteorder("=")
    if header.format == "ascii":
        what = "ASCII vertex data"
        array = read_ascii_rows(
            data, header.data_offset, header.count, native, source=source, error=PlyFormatError,
            what=what,
        )  # fmt: skip
        return PlyCloud(header, array)
    need = header.count * dtype.itemsize
    if len(data) - header.data_offset < need:
        raise PlyFormatError(
            source,
            f"holds {len(data) - header.data_offset} bytes of vertices, {header.count} need "
            f"{need} (the file is truncated)",
        )
    array = np.frombuffer(data, dtype=dtype, count=header.count, offset=header.data_offset)
    return PlyCloud(header, array.astype(native, copy=False))


def read_ply(path: str | os.PathLike[str]) -> np.ndarray:
    """The vertices of a PLY file as a structured array, one field per property."""
    return read_ply_cloud(Path(path).read_bytes(), path).array


def labelled_ply_bytes(
    cloud: PlyCloud,
    labels: np.ndarray,
    confidence: np.ndarray,
    instances: np.ndarray | None = None,
) -> bytes:
    """The PLY again, in its own format, with every vertex property plus `label` (uint) and
    `confidence` (float), and given `instances`, `instance` (uint); properties of those names
    are replaced."""
    added = {"label": ("uint", labels), "confidence": ("float", confidence)}
    if instances is not None:
        added["instance"] = ("uint", instances)
    kept = [(n, k) for n, k in cloud.header.properties if n not in added]
    properties = (*kept, *((name, kind) for name, (kind, _) in added.items()))
    header = PlyHeader(cloud.header.format, len(labels), properties, cloud.header.comments, 0)
    array = np.empty(len(labels), dtype=header.dtype)
    for name, _ in kept:
        array[name] = cloud.array[name]
    for name, (_, values) in added.items():
        array[name] = values
    lines = ["ply", f"format {header.format} 1.0", *header.comments, f"element vertex {len(array)}"]
    lines += [f"property {kind} {name}" for name, kind in properties]
    text = ("\n".join([*lines, "end_header"]) + "\n").encode("ascii")
    if header.format != "ascii":
        return text + array.tobytes()
    formats = [_ASCII_FORMATS.get(kind, "%d") for _, kind in properties]
    out = io.BytesIO()
    np.savetxt(out, array, fmt=formats, delimiter=" ")
    return text + out.getvalue()
