"""Small trees and weights shared by the Ray tests."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import torch
from conftest import shared_path

from rangeret.io import read_labels, read_scan, write_labels, write_scan
from rangeret.layout import labels_dir, velodyne_dir


def small_weights(folder: Path) -> Path:
    """The small published-layout state_dict (32 x 256, 2 blocks), saved alone like a release file."""
    fixture = torch.load(shared_path("fixtures", "rangeret-cir-small.pt"), weights_only=False)
    path = folder / "cir-small.pt"
    torch.save(fixture["state_dict"], path)
    return path


def build_tree(root: Path, labelled: int = 3, unlabelled: int = 2, seq_test: str = "11") -> Path:
    """Subsampled variants of the real scan: `labelled` in sequence 08 (with labels), the rest in 11."""
    points = read_scan(shared_path("data", "semantickitti-scan", "000000.bin"))
    labels = read_labels(shared_path("data", "semantickitti-scan", "000000.label"))
    for i in range(labelled + unlabelled):
        seq = "08" if i < labelled else seq_test
        sel = slice(i % 5, None, 9 + i)
        write_scan(velodyne_dir(root, seq) / f"{i:06d}.bin", points[sel])
        if seq == "08":
            write_labels(labels_dir(root, seq) / f"{i:06d}.label", labels[sel])
    return root


def tree_bytes(pred: Path) -> dict[str, bytes]:
    """Every prediction file of a tree, by relative path."""
    return {str(p.relative_to(pred)): p.read_bytes() for p in sorted(pred.rglob("*.label"))}


def kill_actor_when(predicate, class_part: str = "ModelWorker", timeout: float = 120.0) -> threading.Thread:
    """In the background, once `predicate()` holds, SIGKILL the process of one live actor whose
    class name contains `class_part` (a real crash, which Ray must recover from)."""
    from ray._private.state import actors  # the GCS view; needs no dashboard

    killed: list[int] = []

    def run() -> None:
        deadline = time.time() + timeout
        while time.time() < deadline and not predicate():
            time.sleep(0.05)
        for actor in actors().values():
            if actor["State"] == "ALIVE" and class_part in actor["ActorClassName"] and actor["Pid"]:
                os.kill(actor["Pid"], signal.SIGKILL)
                killed.append(actor["Pid"])
                return

    thread = threading.Thread(target=run, daemon=True)
    thread.killed = killed  # type: ignore[attr-defined]
    thread.start()
    return thread


__all__ = ["build_tree", "kill_actor_when", "np", "small_weights", "tree_bytes"]
