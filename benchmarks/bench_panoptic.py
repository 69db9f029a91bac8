"""Panoptic instances: time to cluster one scan's thing points into objects (target: at most
10 ms per scan on one core at 64 x 1024).

Run by hand: `python benchmarks/bench_panoptic.py [--rounds N]`. Clusters the real scan
(123,389 points) with its ground-truth classes, projected at 64 x 1024, and prints the median,
10th-90th percentile and extremes of N rounds: with the scan's coordinates, without them
(positions from the range image), and with every class taken for a thing class (every point
clustered: the worst case a scan of this size gives). torch is held to one thread; the clustering
itself makes no BLAS call and runs on one core. Timings need the cores to themselves.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch
from _common import REAL_LABELS, REAL_SCAN, require_real_scan

from rangeret.dataset.labels import semantickitti
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.projection import project
from rangeret.inference.instances import row_gaps, scan_instances
from rangeret.io.scans import read_labels, read_scan

TARGET_MS = 10.0
#: SemanticKITTI's thing classes, as its panoptic benchmark names them.
KITTI_THINGS = (
    "car",
    "bicycle",
    "motorcycle",
    "truck",
    "other-vehicle",
    "person",
    "bicyclist",
    "motorcyclist",
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=101, help="timed calls per case")
    args = parser.parse_args()
    require_real_scan()
    torch.set_num_threads(1)
    clustering_time(args.rounds)
    simulated_panoptic_quality(args)


def clustering_time(rounds: int) -> None:
    """Time per scan of `scan_instances` on the real scan, in three cases."""
    points = read_scan(REAL_SCAN)
    labels = read_labels(REAL_LABELS, len(points))
    config = semantickitti()
    classes = config.to_class(labels & 0xFFFF)
    things = np.isin(config.class_names, KITTI_THINGS)
    projection = project(points, 64, 1024)
    gaps = row_gaps(load_profile("semantickitti"))
    everything = np.ones(config.num_classes, dtype=bool)
    cases = [
        ("thing classes, with xyz", points, things),
        ("thing classes, no xyz", None, things),
        ("every class a thing", points, everything),
    ]
    print(f"instances of one scan ({len(points):,} points, 64 x 1024), {rounds} rounds, 1 thread:")
    for name, xyz, thing_mask in cases:
        ids = scan_instances(projection, xyz, classes, thing_mask, gaps)
        times = timings(
            lambda x=xyz, t=thing_mask: scan_instances(projection, x, classes, t, gaps), rounds
        )
        median = float(np.median(times))
        p10, p90 = np.percentile(times, [10, 90])
        print(
            f"  {name:24} {1e3 * median:7.2f} ms  (p10-p90 {1e3 * p10:.2f}-{1e3 * p90:.2f}, "
            f"min {1e3 * times.min():.2f}, max {1e3 * times.max():.2f})  "
            f"{thing_mask[classes].sum():>7,} thing points  {ids.max():>6,} instances  "
            f"{1e3 * median / TARGET_MS:6.2f} x the {TARGET_MS:.0f} ms target"
        )
    ids = scan_instances(projection, points, classes, things, gaps)
    car = classes == config.class_names.index("car")
    print(
        f"  cars: {np.unique(ids[car]).size} instances found, "
        f"{np.unique(labels[car] >> 16).size} annotated"
    )


def timings(fn: Callable[[], object], rounds: int, warmup: int = 3) -> np.ndarray:
    """Wall time in seconds of each of `rounds` calls of `fn()`, after `warmup` untimed ones."""
    for _ in range(warmup):
        fn()
    times = np.empty(rounds)
    for i in range(rounds):
        start = time.perf_counter()
        fn()
        times[i] = time.perf_counter() - start
    return times


def simulated_panoptic_quality(args: argparse.Namespace) -> None:
    """Panoptic quality of the instances on simulated scans, whose objects are known: not
    measured yet."""
    print("panoptic quality on simulated scans: not measured yet")


if __name__ == "__main__":
    main()
