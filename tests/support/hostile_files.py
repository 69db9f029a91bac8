"""Point-cloud files whose headers ask for more than their bodies hold, or that decode wrongly:
the hostile inputs of the decoded-size bounds, for the library, command-line and gateway tests."""

from __future__ import annotations

import io
import struct

import laspy
import lzf
import numpy as np

from tests.support.point_files import las_bytes, pcd_bytes

#: Padding values (U1) a wide point carries beside x, y, z, intensity: 4,096 bytes a point.
PAD = 4080
WIDE_POINT = 16 + PAD


def wide_compressed_pcd(points: int, pad: int = PAD) -> bytes:
    """A `binary_compressed` PCD of `points` points of x, y, z, intensity (the ones of a small
    ring) and a padding field `_` of `pad` bytes: LZF shrinks it about 90 times."""
    header = (
        "VERSION 0.7\nFIELDS x y z intensity _\nSIZE 4 4 4 4 1\nTYPE F F F F U\n"
        f"COUNT 1 1 1 1 {pad}\nWIDTH {points}\nHEIGHT 1\nPOINTS {points}\n"
        "DATA binary_compressed\n"
    ).encode()
    angle = np.linspace(0, 2 * np.pi, points, endpoint=False, dtype=np.float32)
    columns = [10 * np.cos(angle), 10 * np.sin(angle), np.full(points, -1.0, np.float32)]
    columns.append(np.full(points, 0.5, np.float32))
    raw = b"".join(c.astype("<f4").tobytes() for c in columns) + bytes(points * pad)
    packed = lzf.compress(raw)
    return header + struct.pack("<II", len(packed), len(raw)) + packed


def count_bomb_pcd(count: int = 20_000_000) -> bytes:
    """A PCD of one point whose one field declares COUNT `count` (164 bytes)."""
    header = (
        f"VERSION 0.7\nFIELDS x\nSIZE 4\nTYPE F\nCOUNT {count}\nWIDTH 1\nHEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA binary\n"
    ).encode()
    return header + bytes(164 - len(header))


def colliding_pcd() -> bytes:
    """An ASCII PCD whose field `i` with COUNT 2 gives the column `i__0000`, which it also names."""
    return (
        b"VERSION 0.7\nFIELDS x y z i i__0000\nSIZE 4 4 4 4 4\nTYPE F F F F F\n"
        b"COUNT 1 1 1 2 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n"
        b"1 2 3 4 5 6\n1 2 3 4 5 6\n"
    )


def short_ascii_pcd(rows: int = 1, points: int = 20) -> bytes:
    """An ASCII PCD declaring `points` points that holds `rows` rows."""
    return (
        pcd_bytes(np.ones((rows, 4), np.float32), "ascii")
        .replace(f"WIDTH {rows}\n".encode(), f"WIDTH {points}\n".encode())
        .replace(f"POINTS {rows}\n".encode(), f"POINTS {points}\n".encode())
    )


def bad_lzf_pcd(overflowing: bool) -> bytes:
    """A compressed PCD of 64 points whose LZF stream is garbage, or (`overflowing`) a valid
    stream of twice the data its size word declares."""
    data = pcd_bytes(np.ones((64, 4), np.float32), "binary_compressed")
    start = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    need = 64 * 16
    garbage = b"\xff" * 40
    stream = lzf.compress(bytes(range(256)) * (2 * need // 256)) if overflowing else garbage
    return data[:start] + struct.pack("<II", len(stream), need) + stream


def vlr_bomb_las(vlrs: int = 1_000_000) -> bytes:
    """A 34 KB LAS of 100 points whose header declares `vlrs` VLRs."""
    data = bytearray(las_bytes(np.ones((100, 4), np.float32), compressed=False))
    struct.pack_into("<I", data, 100, vlrs)
    return bytes(data) + bytes(34_000 - len(data))


def huge_laz(points: int = 2**40) -> bytes:
    """A LAZ 1.4 file of 100 points whose header declares `points`."""
    header = laspy.LasHeader(point_format=6, version="1.4")
    las = laspy.LasData(header)
    las.x = las.y = las.z = np.arange(100.0)
    out = io.BytesIO()
    las.write(out, do_compress=True)
    data = bytearray(out.getvalue())
    struct.pack_into("<Q", data, 247, points)
    return bytes(data)


def wide_ply_header(vertices: int, properties: int = 100) -> bytes:
    """A binary PLY header of `vertices` vertices of x, y, z and `properties` more doubles, with
    a few bytes of body."""
    names = ["x", "y", "z", *(f"p{i}" for i in range(properties))]
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {vertices}"]
    lines += [f"property double {name}" for name in names]
    return ("\n".join([*lines, "end_header"]) + "\n").encode() + bytes(64)
