"""A simulated dataset in a profile's own layout: folders of sequences (`rangeret.sim.dataset`)
or a version's tables (`rangeret.sim.nuscenes_tree`), chosen by what the layout is."""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping

from rangeret.dataset.profiles import DatasetProfile
from rangeret.sim.dataset import simulate_dataset
from rangeret.sim.nuscenes_tree import simulate_nuscenes
from rangeret.sim.raycast import SensorConfig


def simulate_tree(
    root: str | os.PathLike[str],
    sequences: Mapping[str, int],
    labelled: Iterable[str] | bool = True,
    sensor: SensorConfig | None = None,
    seed: int = 0,
    progress: bool = False,
    *,
    profile: DatasetProfile,
) -> int:
    """Write `sequences` (name -> number of scans) in the profile's layout under `root`, those
    `labelled` with ground truth; the number of scans written. The same seed writes the same
    bytes."""
    if profile.layout.folders is None:
        return simulate_nuscenes(
            root,
            sequences,
            labelled=labelled,
            sensor=sensor,
            seed=seed,
            progress=progress,
            profile=profile,
        )
    return simulate_dataset(
        root, sequences, labelled, sensor, seed=seed, progress=progress, profile=profile
    )
