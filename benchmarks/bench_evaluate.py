"""Evaluator throughput: bincount accumulation against the official np.add.at formulation.

Scans have the real scan's size (123,389 points); predictions are the ground truth with a third
of the points shuffled. Prints medians and ratios; run by hand (`python benchmarks/bench_evaluate.py`).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from _common import REAL_LABELS, median_time, require_real_scan
from _official import add_at_confusion, read_mapped, remap_table

from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, labels_dir, prediction_path, velodyne_dir
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.selection import DatasetSelection
from rangeret.evaluation.evaluate import evaluate_predictions
from rangeret.evaluation.metrics import confusion_counts
from rangeret.io.scans import KITTI_RECORD, read_labels, write_labels, write_scan

SCANS = 40


def build_tree(root: Path, gt: np.ndarray) -> None:
    rng = np.random.default_rng(0)
    points = np.zeros((gt.size, 4), np.float32)
    for i in range(SCANS):
        name = f"{i:06d}"
        write_scan(
            velodyne_dir(root, "08", layout=KITTI_LAYOUT) / f"{name}.bin",
            points,
            record=KITTI_RECORD,
        )
        write_labels(labels_dir(root, "08", layout=KITTI_LAYOUT) / f"{name}.label", gt)
        pred = gt.copy()
        idx = rng.choice(gt.size, gt.size // 3, replace=False)
        pred[idx] = rng.permutation(pred[idx])
        write_labels(prediction_path(root / "pred", "08", name), pred)


def official_end_to_end(root: Path, table: np.ndarray) -> np.ndarray:
    conf = np.zeros((20, 20), np.int64)
    for i in range(SCANS):
        name = f"{i:06d}"
        gt = read_mapped(labels_dir(root, "08", layout=KITTI_LAYOUT) / f"{name}.label", table)
        pred = read_mapped(prediction_path(root / "pred", "08", name), table)
        conf += add_at_confusion(pred, gt, 20)
    return conf


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    require_real_scan()
    cfg = semantickitti()
    gt_raw = read_labels(REAL_LABELS)
    gt8 = cfg.to_class(gt_raw)
    pred8 = np.random.default_rng(1).permutation(gt8)
    # Each evaluator accumulates the class arrays its own mapping step produces: the official
    # lookup table gives int32, ours uint8; int64 inputs show the generic path too.
    gt32, pred32 = gt8.astype(np.int32), pred8.astype(np.int32)
    gt64, pred64 = gt8.astype(np.int64), pred8.astype(np.int64)

    t_add_at = median_time(lambda: add_at_confusion(pred32, gt32, 20), repeat=15, number=20)
    t_ours = median_time(lambda: confusion_counts(pred8, gt8, 20), repeat=15, number=20)
    t_generic = median_time(lambda: confusion_counts(pred64, gt64, 20), repeat=15, number=20)
    print(f"accumulation of one scan ({gt8.size:,} points), median of 15 x 20 calls:")
    print(f"  np.add.at, int32 classes (official)  {1e3 * t_add_at:8.3f} ms")
    print(
        f"  bincount, uint8 classes (ours)       {1e3 * t_ours:8.3f} ms   {t_add_at / t_ours:5.1f} x"
    )
    print(
        f"  bincount, int64 classes (generic)    {1e3 * t_generic:8.3f} ms   {t_add_at / t_generic:5.1f} x"
    )

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        build_tree(root, gt_raw)
        table = remap_table(cfg)
        ours = evaluate_predictions(
            DatasetSelection.named(root, ["08"], KITTI_LAYOUT),
            root / "pred",
            profile=load_profile("semantickitti"),
        )
        assert np.array_equal(ours.confusion.matrix, official_end_to_end(root, table))
        t_official = median_time(lambda: official_end_to_end(root, table), repeat=9)
        t_ours = median_time(
            lambda: evaluate_predictions(
                DatasetSelection.named(root, ["08"], KITTI_LAYOUT),
                root / "pred",
                profile=load_profile("semantickitti"),
            ),
            repeat=9,
        )
    print(f"end to end, {SCANS} scans read from disk, mapped and accumulated, median of 9:")
    print(
        f"  official formulation    {1e3 * t_official / SCANS:8.2f} ms/scan ({SCANS / t_official:6.1f} scans/s)"
    )
    print(
        f"  rangeret evaluate       {1e3 * t_ours / SCANS:8.2f} ms/scan ({SCANS / t_ours:6.1f} scans/s)"
    )
    print(f"  speed-up                {t_official / t_ours:8.1f} x")


if __name__ == "__main__":
    main()
