"""Panoptic instances: time to cluster one scan's thing points into objects (target: at most
10 ms per scan on one core at 64 x 1024), and the panoptic quality they give.

Run by hand: `python benchmarks/bench_panoptic.py [--rounds N] [--scans N] [--angles ...]`.
Clusters the real scan
(123,389 points) with its ground-truth classes, projected at 64 x 1024, and prints the median,
10th-90th percentile and extremes of N rounds: with the scan's coordinates, without them
(positions from the range image), and with every class taken for a thing class (every point
clustered: the worst case a scan of this size gives). torch is held to one thread; the clustering
itself makes no BLAS call and runs on one core. Timings need the cores to themselves.

Then, for each angle threshold, the panoptic quality (SemanticKITTI's rules) of the objects found:
on the real scan from its ground-truth classes (the clustering's own ceiling on real data), and
on simulated scans of sequence 08 both from the bundled demo weights' predicted classes
(`predict --panoptic`) and from the ground-truth classes at the same resolution.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from _common import REAL_LABELS, REAL_SCAN, require_real_scan

from rangeret.dataset.labels import semantickitti
from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.dataset.projection import project, project_with
from rangeret.dataset.selection import DatasetSelection
from rangeret.evaluation.panoptic import KITTI_PANOPTIC
from rangeret.evaluation.panoptic_evaluate import evaluate_panoptic, panoptic_counter
from rangeret.inference.instances import row_gaps, scan_instances
from rangeret.inference.predictor import Predictor
from rangeret.inference.runner import predict_tree
from rangeret.inference.settings import ClusterSettings
from rangeret.inference.spec import InferenceSpec
from rangeret.io.panoptic_labels import SHIFTED
from rangeret.io.scans import read_labels, read_scan
from rangeret.sim import simulate_dataset

TARGET_MS = 10.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=101, help="timed calls per case")
    parser.add_argument("--scans", type=int, default=4, help="simulated scans scored")
    parser.add_argument(
        "--angles", type=float, nargs="+", default=[5.0, 10.0, 15.0, 20.0], help="thresholds"
    )
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
    things = np.isin(np.arange(config.num_classes), load_profile("semantickitti").things)
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


def oracle_counts(
    profile: DatasetProfile, scans: list[tuple[np.ndarray, np.ndarray]], angle: float
) -> dict[str, float]:
    """PQ (overall and things) and mIoU of the objects clustered from the scans' ground-truth
    classes at the profile's resolution, scored as SemanticKITTI's panoptic benchmark."""
    counts = panoptic_counter(profile, KITTI_PANOPTIC, None)
    gaps = row_gaps(profile)
    for points, labels in scans:
        classes = profile.labels.to_class(labels & 0xFFFF)
        projection = project_with(points, profile.projection)
        ids = scan_instances(
            projection, points, classes, profile.things, gaps, ClusterSettings(angle)
        )
        predicted = SHIFTED.encode(labels & 0xFFFF, ids, classes)
        counts.add(classes, predicted, classes, labels)
    return _headline(counts, profile)


def _headline(counts, profile: DatasetProfile) -> dict[str, float]:
    scores = counts.scores(profile.labels.class_names)
    return {
        "pq": scores.mean(scores.pq, scores.evaluated),
        "pq_things": scores.mean(scores.pq, scores.things),
        "miou": scores.mean(scores.iou, scores.evaluated),
    }


def simulated_panoptic_quality(args: argparse.Namespace) -> None:
    """PQ of the clustering at each angle: real scan and simulated scans from ground-truth
    classes, simulated scans from the demo weights' classes."""
    kitti = load_profile("semantickitti")
    real = [(read_scan(REAL_SCAN), None)]
    real = [(points, read_labels(REAL_LABELS, len(points))) for points, _ in real]
    base = Predictor.from_spec(InferenceSpec(panoptic=True))
    demo = base.profile
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "sim"
        simulate_dataset(root, {"08": args.scans}, profile=kitti, seed=11)
        selection = DatasetSelection.named(root, ["08"], kitti.layout).for_task(True)
        simulated = [
            (read_scan(e.scan_path), read_labels(e.label_path))
            for e in selection.scans()
            if e.label_path is not None
        ]
        print(
            f"\npanoptic quality (SemanticKITTI rules, {KITTI_PANOPTIC.min_points}-point minimum), "
            f"real scan at 64 x 1024 and {len(simulated)} simulated scans at "
            f"{demo.projection.height} x {demo.projection.width}:"
        )
        print(
            f"  {'angle':>5}  {'real, GT classes':>22}  {'sim, GT classes':>22}  "
            f"{'sim, demo weights':>30}"
        )
        print(
            f"  {'deg':>5}  {'PQ':>6} {'PQ th':>6} {'mIoU':>6}  {'PQ':>6} {'PQ th':>6} "
            f"{'mIoU':>6}  {'PQ':>6} {'PQ th':>6} {'mIoU':>6} {'ms/scan':>8}"
        )
        for angle in args.angles:
            ceiling_real = oracle_counts(kitti, real, angle)
            ceiling_sim = oracle_counts(demo, simulated, angle)
            out = Path(tmp) / f"pred-{angle:g}"
            predictor = base.with_clustering(ClusterSettings(angle))
            summary = predict_tree(predictor, selection, out, progress=False)
            report = evaluate_panoptic(
                selection,
                out,
                profile=kitti,
                rules=KITTI_PANOPTIC,
                benchmark="semantickitti-panoptic",
            )
            predicted = _headline(report.overall, kitti)
            cluster_ms = summary.times.per_scan_ms().get("cluster", float("nan"))
            cells = [
                f"{100 * r[k]:6.2f}"
                for r in (ceiling_real, ceiling_sim, predicted)
                for k in ("pq", "pq_things", "miou")
            ]
            print(
                f"  {angle:5g}  {' '.join(cells[:3])}  {' '.join(cells[3:6])}  "
                f"{' '.join(cells[6:])} {cluster_ms:8.2f}"
            )


if __name__ == "__main__":
    main()
