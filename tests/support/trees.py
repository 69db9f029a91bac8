"""Small dataset trees on disk, written with the library's own writers."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangeret.dataset.layout import KITTI_LAYOUT
from rangeret.io.scans import KITTI_RECORD


def make_tree(
    root: Path,
    scans: dict[str, list[int]],
    labelled: bool = True,
    seed: int = 0,
) -> dict[str, list[np.ndarray]]:
    """Write a small SemanticKITTI tree: for each sequence, one random scan per point count.

    Labels are random raw ids of the label configuration (with instance bits set on some) and
    are returned per sequence, in scan order.
    """
    from rangeret.dataset.labels import semantickitti
    from rangeret.dataset.layout import labels_dir, velodyne_dir
    from rangeret.io.scans import write_labels, write_scan

    rng = np.random.default_rng(seed)
    raw_ids = np.array(sorted(semantickitti().raw_to_class), dtype=np.uint32)
    written: dict[str, list[np.ndarray]] = {}
    for seq, counts in scans.items():
        velodyne_dir(root, seq, layout=KITTI_LAYOUT).mkdir(parents=True, exist_ok=True)
        written[seq] = []
        for i, n in enumerate(counts):
            points = rng.normal(0, 10, size=(n, 4)).astype(np.float32)
            write_scan(
                velodyne_dir(root, seq, layout=KITTI_LAYOUT) / f"{i:06d}.bin",
                points,
                record=KITTI_RECORD,
            )
            labels = rng.choice(raw_ids, size=n) | (rng.integers(0, 3, n).astype(np.uint32) << 16)
            written[seq].append(labels)
            if labelled:
                write_labels(labels_dir(root, seq, layout=KITTI_LAYOUT) / f"{i:06d}.label", labels)
    return written
