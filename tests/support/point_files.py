"""Point clouds written as PCD, PLY and LAS/LAZ files by other tools' rules, for the tests of
`rangeret.io.point_files` and of what reads through it.

PCD binary and binary_compressed files are written by pypcd4; ASCII PCD and every PLY are written
here by hand with `%.9g`, which gives float32 values back exact. LAS stores scaled integers, so a
LAS file does not hold the float32 values it was made from: `las_decoded` gives the points as the
file holds them, for comparisons against a `.bin` of those.
"""

from __future__ import annotations

import io
from pathlib import Path

import laspy
import numpy as np
from pypcd4 import Encoding, PointCloud

#: The columns of the real scan's record, as a PCD or PLY names them.
FIELDS = ("x", "y", "z", "intensity")
#: LAS coordinate scale used here (0.1 mm).
LAS_SCALE = 1e-4


def pcd_bytes(points: np.ndarray, encoding: str, fields: tuple[str, ...] = FIELDS) -> bytes:
    """float32 (N, len(fields)) points as a PCD file of `encoding`."""
    if encoding == "ascii":
        header = (
            "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
            f"FIELDS {' '.join(fields)}\nSIZE {' '.join(['4'] * len(fields))}\n"
            f"TYPE {' '.join(['F'] * len(fields))}\nCOUNT {' '.join(['1'] * len(fields))}\n"
            f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\n"
            "DATA ascii\n"
        )
        out = io.BytesIO()
        np.savetxt(out, points, fmt="%.9g")
        return header.encode() + out.getvalue()
    cloud = PointCloud.from_points(
        [points[:, i] for i in range(len(fields))], fields, [np.float32] * len(fields)
    )
    out = io.BytesIO()
    cloud.save(out, encoding=Encoding(encoding))
    return out.getvalue()


def ply_bytes(points: np.ndarray, fmt: str, fields: tuple[str, ...] = FIELDS) -> bytes:
    """float32 (N, len(fields)) points as a PLY of `fmt`, with an empty face element after."""
    header = f"ply\nformat {fmt} 1.0\ncomment written by the tests\nelement vertex {len(points)}\n"
    header += "".join(f"property float {f}\n" for f in fields)
    header += "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    if fmt == "ascii":
        out = io.BytesIO()
        np.savetxt(out, points, fmt="%.9g")
        return header.encode() + out.getvalue()
    order = "<" if fmt == "binary_little_endian" else ">"
    return header.encode() + points.astype(f"{order}f4").tobytes()


def las_bytes(points: np.ndarray, compressed: bool) -> bytes:
    """(N, 4) x, y, z, remission points as LAS 1.2 (LAZ when `compressed`): coordinates at
    0.1 mm, remission as uint16 intensity * 65535."""
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = [LAS_SCALE] * 3
    header.offsets = [0.0, 0.0, 0.0]
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.intensity = np.round(np.clip(points[:, 3], 0, 1) * 65535).astype(np.uint16)
    out = io.BytesIO()
    las.write(out, do_compress=compressed)
    return out.getvalue()


def las_decoded(data: bytes) -> np.ndarray:
    """float32 (N, 4) points as a LAS file holds them: scaled coordinates, intensity / 65535."""
    las = laspy.read(io.BytesIO(data))
    return np.stack(
        [np.asarray(las.x), np.asarray(las.y), np.asarray(las.z), las.intensity / 65535.0], axis=1
    ).astype(np.float32)


def write_all_formats(points: np.ndarray, folder: Path) -> dict[str, Path]:
    """The (N, 4) points as every format and encoding, named `<kind>.<ext>` in `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {
        "pcd-ascii": ("pcd", pcd_bytes(points, "ascii")),
        "pcd-binary": ("pcd", pcd_bytes(points, "binary")),
        "pcd-compressed": ("pcd", pcd_bytes(points, "binary_compressed")),
        "ply-ascii": ("ply", ply_bytes(points, "ascii")),
        "ply-le": ("ply", ply_bytes(points, "binary_little_endian")),
        "ply-be": ("ply", ply_bytes(points, "binary_big_endian")),
        "las": ("las", las_bytes(points, False)),
        "laz": ("laz", las_bytes(points, True)),
    }
    paths = {}
    for kind, (ext, data) in files.items():
        paths[kind] = folder / f"{kind}.{ext}"
        paths[kind].write_bytes(data)
    return paths
