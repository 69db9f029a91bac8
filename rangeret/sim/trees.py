"""A simulated dataset in a profile's own layout: folders of sequences (`rangeret.sim.dataset`)
or a version's tables (`rangeret.sim.nuscenes_tree`), chosen by what the layout is."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

from rangeret.dataset.profiles import DatasetProfile
from rangeret.sim.dataset import simulate_dataset
from rangeret.sim.nuscenes_tree import simulate_nuscenes


def simulate_tree(
    root: str | os.PathLike[str],
    sequences: Mapping[str, int],
    *,
    profile: DatasetProfile,
    **options: Any,
) -> int:
    """Write `sequences` (name -> number of scans) in the profile's layout under `root`, with the
    `options` both writers take (`labelled`, `sensor`, `seed`, `progress`); the number of scans
    written."""
    write = simulate_nuscenes if profile.layout.folders is None else simulate_dataset
    return write(root, sequences, profile=profile, **options)
