"""Shared test fixtures: the real scan, label configuration and test vectors of `tests/data`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "tests" / "data"


def data_path(*parts: str) -> Path:
    """A file under `tests/data` (see its README); a failure when it is missing."""
    path = DATA.joinpath(*parts)
    if not path.exists():
        pytest.fail(f"{path} is missing: the repository carries it in tests/data")
    return path


def load_vectors(name: str) -> dict:
    """A test-vector file of `tests/data`, with its float16-stored `state_dict` and `input` upcast
    to float32 (exactly the weights and input its logits were computed from)."""
    import torch

    vectors = torch.load(data_path(name), weights_only=False)
    vectors["state_dict"] = {
        k: v.float() if v.is_floating_point() else v for k, v in vectors["state_dict"].items()
    }
    vectors["input"] = vectors["input"].float()
    return vectors


@pytest.fixture(scope="session")
def real_scan_path() -> Path:
    """The real SemanticKITTI scan (123,389 points)."""
    return data_path("semantickitti-scan", "000000.bin")


@pytest.fixture(scope="session")
def real_label_path() -> Path:
    """Ground-truth labels of the real scan."""
    return data_path("semantickitti-scan", "000000.label")


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
