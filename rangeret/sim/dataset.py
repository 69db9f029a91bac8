"""The dataset writer: sequences of simulated scans in the SemanticKITTI layout.

Each sequence gets its own street, along which the sensor drives one scan period per scan.
`simulate_dataset` writes the tree, reproducible byte for byte from its seed.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping

import numpy as np

from rangeret.atomic import atomic_write_bytes
from rangeret.io import write_labels, write_scan
from rangeret.layout import labels_dir, normalise_sequence, velodyne_dir
from rangeret.sim.raycast import SensorConfig, simulate_scan
from rangeret.sim.scene import make_scene

#: Seconds between two scans (the HDL-64E spins at 10 Hz).
SCAN_PERIOD = 0.1


def _sequence_seed(seed: int, name: str) -> np.random.SeedSequence:
    """The seed of one sequence: the dataset seed and the sequence's name."""
    return np.random.SeedSequence(seed, spawn_key=tuple(name.encode("utf-8")))


def _matrix_line(values: Iterable[float]) -> str:
    """One row-major matrix as a line of the KITTI text files (poses, calibration)."""
    return " ".join(f"{v:.12e}" for v in values)


def simulate_dataset(
    root: str | os.PathLike[str],
    sequences: Mapping[str, int],
    labelled: Iterable[str] | bool = True,
    sensor: SensorConfig | None = None,
    seed: int = 0,
    progress: bool = False,
) -> int:
    """Write a simulated SemanticKITTI tree under `root` and return the number of scans written.

    `sequences` maps a sequence name to its number of scans. Each sequence gets its own street
    and writes `sequences/XX/velodyne/NNNNNN.bin`, `labels/NNNNNN.label` when it is labelled
    (`labelled`: True for all, False for none, or the names of the labelled ones), and
    `poses.txt`, `times.txt` and `calib.txt` (the LiDAR is the reference frame: `Tr` is the
    identity and the poses are the sensor's). The same seed writes the same bytes.
    """
    sensor = sensor or SensorConfig()
    counts = {normalise_sequence(name): int(n) for name, n in sequences.items()}
    if any(n < 0 for n in counts.values()):
        raise ValueError(f"numbers of scans must be >= 0, got {counts}")
    if isinstance(labelled, bool):
        with_labels = set(counts) if labelled else set()
    else:
        with_labels = {normalise_sequence(name) for name in labelled}
        unknown = sorted(with_labels - set(counts))
        if unknown:
            raise ValueError(f"labelled sequences {unknown} are not among the sequences")

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(counts.values()), unit="scan", desc="simulating")
    written = 0
    try:
        for name, n in counts.items():
            seeds = _sequence_seed(seed, name).spawn(n + 1)
            scene = make_scene(np.random.default_rng(seeds[0]), max(200.0, 1.25 * n))
            step = scene.ego_speed * SCAN_PERIOD
            seq_dir = velodyne_dir(root, name).parent
            seq_dir.mkdir(parents=True, exist_ok=True)
            poses, times = [], []
            for k in range(n):
                points, labels = simulate_scan(
                    scene, k * step, sensor, np.random.default_rng(seeds[k + 1])
                )
                write_scan(velodyne_dir(root, name) / f"{k:06d}.bin", points)
                if name in with_labels:
                    write_labels(labels_dir(root, name) / f"{k:06d}.label", labels)
                poses.append(_matrix_line([1, 0, 0, k * step, 0, 1, 0, 0, 0, 0, 1, 0]))
                times.append(f"{k * SCAN_PERIOD:.6e}")
                written += 1
                if bar is not None:
                    bar.update(1)
            identity = _matrix_line([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0])
            calib = [f"P{i}: {identity}" for i in range(4)] + [f"Tr: {identity}"]
            for file, lines in (("poses.txt", poses), ("times.txt", times), ("calib.txt", calib)):
                atomic_write_bytes(seq_dir / file, "".join(f"{x}\n" for x in lines).encode())
    finally:
        if bar is not None:
            bar.close()
    return written
