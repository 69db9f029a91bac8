"""From logits to one class per point: the per-pixel argmax, then pixel lookup or kNN refinement.

Written once for every runner: `Predictor.refine_batch` (one call per batch) and the trainer's
validation share `pixel_classes` and `point_classes_batch`, so the labels measured during
training are the labels served.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence

import numpy as np
import torch

from rangeret.inference.knn import flat_pixels, refine_batch
from rangeret.inference.settings import KnnSettings

#: A scan's projection array: numpy, as a `Projection` holds it, or a tensor holding one (a
#: data loader's).
ProjectionArray = np.ndarray | torch.Tensor


def pixel_classes(logits: torch.Tensor, first: int = 0) -> torch.Tensor:
    """(B, H, W) int64: each pixel's class among first..C-1 of (B, C, H, W) `logits` (the first of
    equal maxima, as `torch.argmax`).

    On the CPU taken with the classes innermost: torch's argmax across the class axis of a
    (B, C, H, W) tensor strides through memory there, several times slower than a copy to
    (B, H, W, C) and an argmax along its rows (12 ms against under 3 ms for 20 classes at
    64 x 1024). A GPU's reduction reads the strided axis well, so it is spared the copy.
    """
    scores = logits[:, first:] if first else logits
    if scores.device.type == "cpu":
        scores = scores.permute(0, 2, 3, 1).contiguous().movedim(-1, 1)
    choice = scores.argmax(dim=1)
    return choice + first if first else choice


def point_classes_batch(
    argmax: torch.Tensor,
    proj_x: Sequence[ProjectionArray],
    proj_y: Sequence[ProjectionArray],
    proj_range: Sequence[ProjectionArray],
    unproj_range: Sequence[ProjectionArray],
    knn: KnnSettings | None,
    num_classes: int,
    votes_from: int = 1,
    unlabeled: int = 0,
) -> torch.Tensor:
    """(N,) int64 classes of B scans' points, concatenated scan by scan, on argmax's device, from
    their (B, H, W) argmax and each scan's projection arrays.

    Without `knn` each point takes its pixel's class; with it, the kNN vote in range decides
    among classes votes_from..C-1 (the dataset profile's rule). Points without a pixel
    (proj_x == -1) get the `unlabeled` class either way. The arrays go to the device in one copy
    each, so the batch costs the device no wait on the host, however many scans it holds.
    """
    device = argmax.device
    proj_x, proj_y, proj_range, unproj_range = (
        [_on_host(part) for part in parts] for parts in (proj_x, proj_y, proj_range, unproj_range)
    )
    if knn is None:
        _, height, width = argmax.shape
        pixels = flat_pixels(proj_x, proj_y, height, width, device)
        looked_up = argmax.to(torch.int64).reshape(-1).index_select(0, pixels.clamp(min=0))
        return torch.where(pixels >= 0, looked_up, unlabeled)
    with single_thread_on_cpu(device):
        return refine_batch(
            argmax,
            proj_range,
            unproj_range,
            proj_x,
            proj_y,
            knn,
            num_classes,
            votes_from=votes_from,
            unprojected=unlabeled,
        )


def _on_host(value: ProjectionArray) -> np.ndarray:
    """A projection array as a numpy array (a CPU tensor's own memory, no copy)."""
    return value.numpy(force=True) if isinstance(value, torch.Tensor) else np.asarray(value)


@contextlib.contextmanager
def single_thread_on_cpu(device: torch.device) -> Iterator[None]:
    """Run the body on one torch thread when on the CPU.

    kNN refinement on the CPU runs on as many threads as torch has (`refine_batch`); beside the
    readers of a pipeline those would compete with them for the same cores, while one thread
    leaves them the others (`benchmarks/bench_knn.py` measures both).
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
