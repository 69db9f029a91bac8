"""The official SemanticKITTI evaluation written the slow, direct way, as an independent reference.

Labels are read as int32, masked to 16 bits, mapped through a lookup table 100 entries longer
than the largest known raw id, and counted into C[pred, gt] with `np.add.at`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangeret.dataset.labels import LabelConfig


def remap_table(config: LabelConfig) -> np.ndarray:
    """Lookup table raw id -> class, sized as the official evaluator sizes it."""
    table = np.zeros(max(config.raw_to_class) + 100, dtype=np.int32)
    table[list(config.raw_to_class)] = list(config.raw_to_class.values())
    return table


def read_mapped(path: Path, table: np.ndarray) -> np.ndarray:
    """A label file as training classes, the official way."""
    return table[np.fromfile(path, dtype=np.int32).reshape(-1) & 0xFFFF]


def add_at_confusion(pred: np.ndarray, gt: np.ndarray, num_classes: int) -> np.ndarray:
    """C[pred, gt] accumulated with np.add.at."""
    conf = np.zeros((num_classes, num_classes), dtype=np.int64)
    np.add.at(conf, (pred.reshape(-1), gt.reshape(-1)), 1)
    return conf


def scores(conf: np.ndarray, ignore: list[int]) -> tuple[float, np.ndarray, float]:
    """(mIoU, per-class IoU, accuracy) from a confusion matrix, the official way."""
    n = conf.shape[0]
    include = [c for c in range(n) if c not in ignore]
    c = conf.copy()
    c[:, ignore] = 0
    tp = np.diag(c)
    fp = c.sum(axis=1) - tp
    fn = c.sum(axis=0) - tp
    union = tp + fp + fn + 1e-15
    iou = tp / union
    miou = (tp[include] / union[include]).mean()
    acc = tp.sum() / (tp[include].sum() + fp[include].sum() + 1e-15)
    return float(miou), iou, float(acc)
