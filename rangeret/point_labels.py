"""From a range image's per-pixel classes to one class per point: pixel lookup or kNN refinement.

Written once for every runner: `Predictor` and the trainer's validation both call
`point_classes`, so the labels measured during training are the labels served.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass

import torch

from rangeret.knn import refine


@dataclass(frozen=True)
class KnnSettings:
    """kNN refinement parameters; the defaults are those the released checkpoints were scored with."""

    k: int = 7
    search: int = 7
    sigma: float = 1.0
    cutoff: float = 1.0


#: The refinement every runner applies unless told otherwise.
DEFAULT_KNN = KnnSettings()


def point_classes(
    argmax: torch.Tensor,
    proj_x: torch.Tensor,
    proj_y: torch.Tensor,
    proj_range: torch.Tensor,
    unproj_range: torch.Tensor,
    knn: KnnSettings | None,
    num_classes: int,
    votes_from: int = 1,
    unlabeled: int = 0,
) -> torch.Tensor:
    """(N,) int64 classes on argmax's device from an (H, W) argmax and the scan's projection.

    Without `knn` each point takes its pixel's class; with it, the kNN vote in range decides
    among classes votes_from..C-1 (the dataset profile's rule). Points without a pixel
    (proj_x == -1) get the `unlabeled` class either way.
    """
    device = argmax.device
    proj_x, proj_y = proj_x.to(device), proj_y.to(device)
    if knn is None:
        valid = proj_x >= 0
        classes = torch.full((proj_x.shape[0],), unlabeled, dtype=torch.int64, device=device)
        classes[valid] = argmax[proj_y[valid], proj_x[valid]].to(torch.int64)
        return classes
    with single_thread_on_cpu(device):
        return refine(
            proj_range.to(device),
            unproj_range.to(device),
            argmax,
            proj_x,
            proj_y,
            k=knn.k,
            search=knn.search,
            sigma=knn.sigma,
            cutoff=knn.cutoff,
            num_classes=num_classes,
            votes_from=votes_from,
            unprojected=unlabeled,
        )


@contextlib.contextmanager
def single_thread_on_cpu(device: torch.device) -> Iterator[None]:
    """Run the body on one torch thread when on the CPU.

    kNN refinement is many small operations: with several threads, each waits for a time slice
    whenever the cores are shared (readers beside the model actor), which can make it a hundred
    times slower; on one thread it costs about 1.5x its best time and never more.
    """
    if device.type != "cpu":
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
