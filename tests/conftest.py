"""Shared test fixtures: the `../shared` folder with the real scan and test vectors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"


def shared_path(*parts: str) -> Path:
    """A file under `../shared`: skipped when absent outside CI, a failure when absent under CI."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        if os.environ.get("CI") == "true":
            pytest.fail(f"{path} is missing, and CI must have ../shared beside the project")
        pytest.skip(
            f"{path} is not here (../shared is only beside the project on CI and dev machines)"
        )
    return path


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The `../shared` folder (skip when absent outside CI, fail when absent under CI)."""
    return shared_path()


@pytest.fixture(scope="session")
def real_scan_path() -> Path:
    """The real SemanticKITTI scan (123,389 points)."""
    return shared_path("data", "semantickitti-scan", "000000.bin")


@pytest.fixture(scope="session")
def real_label_path() -> Path:
    """Ground-truth labels of the real scan."""
    return shared_path("data", "semantickitti-scan", "000000.label")


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
    from rangeret.io import write_labels, write_scan
    from rangeret.labels import semantickitti
    from rangeret.layout import labels_dir, velodyne_dir

    rng = np.random.default_rng(seed)
    raw_ids = np.array(sorted(semantickitti().raw_to_class), dtype=np.uint32)
    written: dict[str, list[np.ndarray]] = {}
    for seq, counts in scans.items():
        velodyne_dir(root, seq).mkdir(parents=True, exist_ok=True)
        written[seq] = []
        for i, n in enumerate(counts):
            points = rng.normal(0, 10, size=(n, 4)).astype(np.float32)
            write_scan(velodyne_dir(root, seq) / f"{i:06d}.bin", points)
            labels = rng.choice(raw_ids, size=n) | (rng.integers(0, 3, n).astype(np.uint32) << 16)
            written[seq].append(labels)
            if labelled:
                write_labels(labels_dir(root, seq) / f"{i:06d}.label", labels)
    return written
