"""Projection time per scan on the real 123,389-point scan (target: at most 20 ms on 2 cores).

Run by hand: `python benchmarks/bench_projection.py`. Prints medians; not a test.
"""

from __future__ import annotations

import argparse

from _common import REAL_SCAN, median_time, require_real_scan

from rangeret.dataset.projection import project
from rangeret.io.scans import read_scan

TARGET_MS = 20.0


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    require_real_scan()
    points = read_scan(REAL_SCAN)
    print(f"projection of one scan ({len(points):,} points), median of 31 runs:")
    for h, w in [(64, 512), (64, 1024), (64, 2048)]:
        t = median_time(lambda h=h, w=w: project(points, h, w), repeat=31)
        filled = project(points, h, w).mask.sum()
        print(
            f"  {h} x {w:<5} {1e3 * t:7.2f} ms   {filled:>6,} pixels filled "
            f"({100 * filled / (h * w):4.1f} %)   {TARGET_MS / (1e3 * t):4.1f} x under the {TARGET_MS:.0f} ms target"
        )
    t_read = median_time(lambda: read_scan(REAL_SCAN), repeat=31)
    print(f"  reading the .bin file: {1e3 * t_read:.2f} ms")


if __name__ == "__main__":
    main()
