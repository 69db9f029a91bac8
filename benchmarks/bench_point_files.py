"""Read and write throughput of every point-cloud file format on the real 123,389-point scan.

For each format and encoding: reading the file's bytes into columns (`decode_point_file`) and
writing its labelled copy (`labelled_bytes`: the file with `label` and `confidence` added), as
points/s and MB/s of the file, medians over repeats. The PCD and PLY inputs are the labelled
writer's own output (x, y, z, intensity, label, confidence); the LAS and LAZ ones are written by
laspy (point format 1, 0.1 mm). Run by hand:
`python benchmarks/bench_point_files.py [--repeat N]`. Prints a table; not a test.
"""

from __future__ import annotations

import argparse
import io

import numpy as np
from _common import REAL_SCAN, median_time, require_real_scan

from rangeret.extras import require_extra
from rangeret.io import pcd, ply
from rangeret.io.point_files import PointFile, decode_point_file, labelled_bytes
from rangeret.io.scans import KITTI_RECORD, read_scan

FIELDS = ("x", "y", "z", "intensity")


def _pcd_file(points: np.ndarray, encoding: str) -> bytes:
    """The scan as a PCD of `encoding`, as the labelled writer writes it."""
    n = len(points)
    header = pcd.PcdHeader(FIELDS, (4,) * 4, ("F",) * 4, (1,) * 4, n, 1, n, encoding, 0)
    array = np.rec.fromarrays(points.T, names=list(FIELDS)).astype(header.dtype)
    return pcd.labelled_pcd_bytes(pcd.PcdCloud(header, array), np.zeros(n), np.zeros(n))


def _ply_file(points: np.ndarray, fmt: str) -> bytes:
    """The scan as a PLY of `fmt`, as the labelled writer writes it."""
    n = len(points)
    header = ply.PlyHeader(fmt, n, tuple((f, "float") for f in FIELDS), (), 0)
    array = np.rec.fromarrays(points.T, names=list(FIELDS)).astype(header.dtype.newbyteorder("="))
    return ply.labelled_ply_bytes(ply.PlyCloud(header, array), np.zeros(n), np.zeros(n))


def _las_file(points: np.ndarray, compressed: bool) -> bytes:
    """The scan as LAS 1.2 point format 1 at 0.1 mm (LAZ when `compressed`)."""
    import laspy

    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [1e-4] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.intensity = np.round(np.clip(points[:, 3], 0, 1) * 65535).astype(np.uint16)
    out = io.BytesIO()
    las.write(out, do_compress=compressed)
    return out.getvalue()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=7, help="timed runs per figure (median)")
    args = parser.parse_args()
    require_real_scan()
    require_extra("benchmarks/bench_point_files.py", "files")
    points = read_scan(REAL_SCAN)
    n = len(points)
    files = {
        ("bin", "float32 records"): ("bin", points.tobytes()),
        ("pcd", "ascii"): ("pcd", _pcd_file(points, "ascii")),
        ("pcd", "binary"): ("pcd", _pcd_file(points, "binary")),
        ("pcd", "binary_compressed"): ("pcd", _pcd_file(points, "binary_compressed")),
        ("ply", "ascii"): ("ply", _ply_file(points, "ascii")),
        ("ply", "binary_little_endian"): ("ply", _ply_file(points, "binary_little_endian")),
        ("ply", "binary_big_endian"): ("ply", _ply_file(points, "binary_big_endian")),
        ("las", "uncompressed"): ("las", _las_file(points, False)),
        ("laz", "lazrs"): ("las", _las_file(points, True)),
    }
    labels = np.arange(n, dtype=np.uint32) % 20
    confidence = np.full(n, 0.5, dtype=np.float32)
    print(f"point-cloud files of the real scan ({n:,} points), median of {args.repeat} runs:")
    print(f"  {'format':<4} {'encoding':<21} {'MB':>6}  {'read Mpt/s':>10} {'read MB/s':>9}  "
          f"{'write Mpt/s':>11} {'write MB/s':>10}")  # fmt: skip
    for (name, encoding), (fmt, data) in files.items():

        def read(fmt: str = fmt, data: bytes = data) -> PointFile:
            return decode_point_file(data, fmt, record=KITTI_RECORD, source="scan")

        t_read = median_time(read, repeat=args.repeat)
        decoded = read()
        mb = len(data) / 1e6
        if decoded.can_write_labelled:
            t_write = median_time(
                lambda d=decoded: labelled_bytes(d, labels, confidence), repeat=args.repeat
            )
            written_mb = len(labelled_bytes(decoded, labels, confidence)) / 1e6
            write = f"{n / t_write / 1e6:11.2f} {written_mb / t_write:10.1f}"
        else:
            write = f"{'(its .label)':>22}"
        print(
            f"  {name:<4} {encoding:<21} {mb:6.2f}  {n / t_read / 1e6:10.2f} {mb / t_read:9.1f}  "
            f"{write}"
        )


if __name__ == "__main__":
    main()
