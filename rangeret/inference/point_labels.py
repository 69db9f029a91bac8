"""From a range image's per-pixel classes to one class per point: pixel lookup or kNN refinement.

Written once for every runner: `Predictor` (`point_classes_batch`, one call per batch) and the
trainer's validation (`point_classes`, one scan) share it, so the labels measured during
training are the labels served.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence

import numpy as np
import torch

from rangeret.inference.knn import pixel_classes, refine_batch
from rangeret.inference.settings import KnnSettings


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
    return point_classes_batch(
        argmax[None],
        [proj_x],
        [proj_y],
        [proj_range],
        [unproj_range],
        knn,
        num_classes,
        votes_from,
        unlabeled,
    )


def point_classes_batch(
    argmax: torch.Tensor,
    proj_x: Sequence[np.ndarray | torch.Tensor],
    proj_y: Sequence[np.ndarray | torch.Tensor],
    proj_range: Sequence[np.ndarray | torch.Tensor],
    unproj_range: Sequence[np.ndarray | torch.Tensor],
    knn: KnnSettings | None,
    num_classes: int,
    votes_from: int = 1,
    unlabeled: int = 0,
) -> torch.Tensor:
    """`point_classes` of B scans in one call: a (B, H, W) argmax and each scan's projection give
    the classes of all their points, concatenated scan by scan, on argmax's device.

    Projection arrays are best given as numpy arrays (CPU tensors are taken as such): they are
    checked on the host and copied to the device in one go, so the batch costs the device a
    fixed number of waits on the host, however many scans and points it holds.
    """
    device = argmax.device
    proj_x, proj_y, proj_range, unproj_range = (
        [_host_or_on(part, device) for part in parts]
        for parts in (proj_x, proj_y, proj_range, unproj_range)
    )
    if knn is None:
        return pixel_classes(argmax, proj_x, proj_y, num_classes, unprojected=unlabeled)
    with single_thread_on_cpu(device):
        return refine_batch(
            proj_range,
            unproj_range,
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


def _host_or_on(
    value: np.ndarray | torch.Tensor, device: torch.device
) -> np.ndarray | torch.Tensor:
    """A CPU tensor as the numpy array it holds, another tensor on `device`, an array as it is."""
    if not isinstance(value, torch.Tensor):
        return value
    return value.numpy() if value.device.type == "cpu" else value.to(device)


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


def point_confidences(
    logits: torch.Tensor,
    proj_x: Sequence[np.ndarray],
    proj_y: Sequence[np.ndarray],
    classes: Sequence[np.ndarray],
) -> list[np.ndarray]:
    """Each point's confidence: the softmax probability, at the point's pixel of (B, C, H, W)
    `logits`, of the class the point was finally given (after kNN); 0 for a point without a
    pixel. One float32 array per scan."""
    probabilities = torch.softmax(logits.float(), dim=1)
    out = []
    for b, (px, py, cls) in enumerate(zip(proj_x, proj_y, classes, strict=True)):
        confidence = np.zeros(len(cls), dtype=np.float32)
        valid = px >= 0
        if valid.any():
            index = [
                torch.from_numpy(np.ascontiguousarray(a[valid], dtype=np.int64)).to(logits.device)
                for a in (cls, py, px)
            ]
            confidence[valid] = probabilities[b, index[0], index[1], index[2]].cpu().numpy()
        out.append(confidence)
    return out
