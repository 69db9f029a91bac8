"""Per-stage time of the single-process pipeline on the real scan, and end-to-end scans/s.

Uses the release-shaped network (`rangeret-cir`, 8 blocks, 64 x 1024, random weights) saved as a
bare state_dict like the release file, and, for comparison, the lighter thesis network. Run by
hand: `python benchmarks/bench_predict.py [--device cuda] [--scans N]`. Prints medians; not a test.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from _common import REAL_SCAN, require_real_scan

from rangeret.dataset.layout import KITTI_LAYOUT, velodyne_dir
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.selection import DatasetSelection
from rangeret.inference.predictor import Predictor
from rangeret.inference.runner import predict_tree
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import KITTI_RECORD, read_scan, write_labels, write_scan
from rangeret.models import build_model


def stage_medians(
    predictor: Predictor, points: np.ndarray, repeat: int, out: Path
) -> dict[str, float]:
    """Median milliseconds of each stage over `repeat` scans."""
    samples: dict[str, list[float]] = {
        k: [] for k in ("read", "project", "network", "knn", "write")
    }
    for i in range(repeat + 1):
        t0 = time.perf_counter()
        pts = read_scan(REAL_SCAN)
        t1 = time.perf_counter()
        proj = predictor.project(pts)
        t2 = time.perf_counter()
        logits = predictor.logits([proj])
        t3 = time.perf_counter()
        [classes] = predictor.refine_batch([proj], logits)
        t4 = time.perf_counter()
        write_labels(out / f"{i}.label", predictor.to_raw(classes))
        t5 = time.perf_counter()
        if i == 0:
            continue  # warm-up
        for key, value in zip(samples, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4), strict=True):
            samples[key].append(1e3 * value)
    return {k: statistics.median(v) for k, v in samples.items()}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="auto")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--scans", type=int, default=6, help="scans in the end-to-end tree")
    args = parser.parse_args()
    require_real_scan()
    points = read_scan(REAL_SCAN)
    release = build_model("rangeret-cir", 64, 1024).state_dict()  # the release's 8-block shape
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        torch.save(release, tmp / "cir.pt")
        cir = Predictor.from_checkpoint(tmp / "cir.pt", device=args.device)
        thesis = Predictor.from_network(
            build_model("rangeret-thesis"), load_profile(), InferenceSpec(device=args.device)
        )
        print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {cir.device}")
        print(f"one scan of {len(points):,} points at 64 x 1024, median of {args.repeat} (ms):")
        print(
            f"  {'network':<16} {'read':>7} {'project':>8} {'network':>9} {'kNN 7x7':>8} {'write':>7} {'total':>8}"
        )
        for name, predictor in (("rangeret-cir", cir), ("rangeret-thesis", thesis)):
            m = stage_medians(predictor, points, args.repeat, tmp)
            print(
                f"  {name:<16} {m['read']:7.1f} {m['project']:8.1f} {m['network']:9.1f} "
                f"{m['knn']:8.1f} {m['write']:7.1f} {sum(m.values()):8.1f}"
            )
        root = tmp / "data"
        for i in range(args.scans):
            write_scan(
                velodyne_dir(root, "08", layout=KITTI_LAYOUT) / f"{i:06d}.bin",
                points[i % 3 :: 1 + i % 2],
                record=KITTI_RECORD,
            )
        for name, predictor in (("rangeret-cir", cir), ("rangeret-thesis", thesis)):
            out = tmp / f"pred-{name}"
            summary = predict_tree(
                predictor, DatasetSelection.named(root, ["08"], KITTI_LAYOUT), out, progress=False
            )
            print(
                f"end to end, rangeret predict over {args.scans} scans, {name}: {summary.written / summary.seconds:.3f} scans/s"
            )


if __name__ == "__main__":
    main()
