"""Coloured point clouds as binary little-endian PLY files, and a reader for such files.

The writer gives one vertex per point with `x`, `y`, `z` (float32), `red`, `green`, `blue`
(uchar) and `label` (uint32, the raw semantic id), under the standard header that CloudCompare,
MeshLab and Open3D read (`label` shows as a scalar field where the viewer has them). The reader
takes any binary little-endian PLY whose first element is `vertex` with scalar properties, as
written here.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rangeret.exceptions import InputError
from rangeret.io.atomic import atomic_write_bytes

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


class PlyFormatError(InputError, ValueError):
    """A PLY file this reader cannot read, naming the file and the problem."""

    def __init__(self, source: str | os.PathLike[str], problem: str) -> None:
        super().__init__(f"{source}: {problem}")


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


def read_ply(path: str | os.PathLike[str]) -> np.ndarray:
    """The vertices of a binary little-endian PLY as a structured array, one field per property."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PlyFormatError(path, "is not a PLY file (no 'ply' magic or no end_header)")
    body = data.index(b"\n", end) + 1
    lines = data[:body].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise PlyFormatError(path, "is not a binary little-endian PLY")
    count, fields = None, []
    for line in lines:
        words = line.split()
        if words[:1] == ["element"]:
            if count is not None:
                break  # only the vertex element, which comes first, is read
            if words[1:2] != ["vertex"]:
                raise PlyFormatError(path, f"the first element is {words[1]!r}, not vertex")
            count = int(words[2])
        elif words[:1] == ["property"] and count is not None:
            if words[1] not in PLY_TYPES:
                raise PlyFormatError(path, f"property {' '.join(words[1:])} is not a scalar")
            fields.append((words[2], PLY_TYPES[words[1]]))
    if count is None:
        raise PlyFormatError(path, "has no vertex element")
    dtype = np.dtype(fields)
    if len(data) - body < count * dtype.itemsize:
        raise PlyFormatError(
            path,
            f"holds {len(data) - body} bytes of vertices, {count} need {count * dtype.itemsize}",
        )
    return np.frombuffer(data, dtype=dtype, count=count, offset=body).copy()
