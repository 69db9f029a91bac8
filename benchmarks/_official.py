"""The baseline the evaluator is timed against: the official evaluator's way of counting.

Labels are read as int32, masked to 16 bits, mapped through a table 100 entries longer than the
largest raw id, and counted into C[pred, gt] with `np.add.at`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangeret.dataset.labels import LabelConfig


def remap_table(config: LabelConfig) -> np.ndarray:
    """Raw id -> class, sized as the official evaluator sizes it."""
    table = np.zeros(max(config.raw_to_class) + 100, dtype=np.int32)
    table[list(config.raw_to_class)] = list(config.raw_to_class.values())
    return table


def read_mapped(path: Path, table: np.ndarray) -> np.ndarray:
    """A label file as training classes, read and mapped the official way."""
    return table[np.fromfile(path, dtype=np.int32).reshape(-1) & 0xFFFF]


def add_at_confusion(pred: np.ndarray, gt: np.ndarray, num_classes: int) -> np.ndarray:
    """C[pred, gt] accumulated one point at a time with np.add.at."""
    conf = np.zeros((num_classes, num_classes), dtype=np.int64)
    np.add.at(conf, (pred.reshape(-1), gt.reshape(-1)), 1)
    return conf
