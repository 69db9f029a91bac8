"""kNN refinement of one scan from arrays of any origin (`rangeret.knn.refine`, a long-standing
path): its inputs checked, then refined as a batch of one by `rangeret.inference.knn`."""

from __future__ import annotations

import numpy as np
import torch

from rangeret.dataset.fields import is_int
from rangeret.dataset.projection import ProjectionError, check_pixels
from rangeret.inference.knn import refine_batch, to_device
from rangeret.inference.settings import KnnSettings

__all__ = ["refine"]

ArrayLike = np.ndarray | torch.Tensor


def refine(
    proj_range: ArrayLike,
    unproj_range: ArrayLike,
    proj_argmax: ArrayLike,
    proj_x: ArrayLike,
    proj_y: ArrayLike,
    k: int = 7,
    search: int = 7,
    sigma: float = 1.0,
    cutoff: float = 1.0,
    num_classes: int = 20,
    *,
    votes_from: int = 1,
    unprojected: int = 0,
    chunk_size: int | None = None,
) -> ArrayLike:
    """Per-point classes from a per-pixel argmax by a kNN vote in range.

    proj_range: (H, W) range of each pixel, -1 where empty. unproj_range: (N,) range of each
    point. proj_argmax: (H, W) integer classes in [0, num_classes). proj_x, proj_y: (N,) column and
    row of each point, proj_x == -1 for points that were not projected (they get `unprojected`).
    k neighbours among the search x search window; Gaussian weight `sigma`; neighbours farther than
    `cutoff` do not vote (no cutoff when it is <= 0). chunk_size bounds the points the exact rule
    in torch takes at once (on devices other than the CPU; default CHUNK_SIZE). Classes
    votes_from..C-1 vote; a point without a vote gets class `votes_from`.

    Returns (N,) int64 classes: a numpy array when every input is a numpy array, otherwise a
    torch tensor on the device of the tensor inputs. Ranges are compared in float32, as the
    published code does. Bad input is a ProjectionError (a ValueError) naming the argument.
    """
    knn = KnnSettings(k, search, sigma, cutoff)
    _check_class_ids(num_classes, votes_from, unprojected)
    if chunk_size is not None and (not is_int(chunk_size) or chunk_size < 1):
        raise ProjectionError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    given = (proj_range, unproj_range, proj_argmax, proj_x, proj_y)
    devices = {x.device for x in given if isinstance(x, torch.Tensor)}
    if len(devices) > 1:
        names = ", ".join(sorted(str(d) for d in devices))
        raise ProjectionError(
            f"the input tensors are on different devices ({names}); move them to one"
        )
    device = next(iter(devices), torch.device("cpu"))
    names = ("proj_range", "unproj_range", "proj_argmax", "proj_x", "proj_y")
    ranges, point_ranges, classes, cols, rows = (
        _host(x, name) for x, name in zip(given, names, strict=True)
    )
    check_pixels(ranges, point_ranges, cols, rows)
    _check_argmax(classes, ranges.shape, num_classes)
    if isinstance(proj_argmax, torch.Tensor):
        argmax = proj_argmax.to(torch.int64)[None]
    else:
        argmax = to_device([classes[None]], torch.int64, device, pinned=device.type == "cuda")
    result = refine_batch(
        argmax,
        [ranges],
        [point_ranges],
        [cols],
        [rows],
        knn,
        num_classes,
        votes_from=votes_from,
        unprojected=unprojected,
        chunk_size=chunk_size,
    )
    return result if devices else result.numpy()


def _host(value: object, name: str) -> np.ndarray:
    """An input as a numpy array (a tensor's values copied to the host if need be)."""
    if not isinstance(value, torch.Tensor):
        return np.asarray(value)
    try:
        return value.numpy(force=True)
    except TypeError as exc:  # a dtype numpy does not have (bfloat16, say)
        raise ProjectionError(f"{name} must hold real numbers, got dtype {value.dtype}") from exc


def _check_argmax(classes: np.ndarray, shape: tuple[int, ...], num_classes: int) -> None:
    """Raise ValueError unless `classes` is an image of class ids of the given shape."""
    if classes.dtype.kind not in "iu":
        raise ProjectionError(f"proj_argmax must hold integers, got dtype {classes.dtype}")
    if classes.shape != shape:
        raise ProjectionError(
            f"proj_argmax must have the shape of proj_range {shape}, got {classes.shape}"
        )
    low, high = (int(classes.min()), int(classes.max())) if classes.size else (0, 0)
    if low < 0 or high >= num_classes:
        raise ProjectionError(
            f"proj_argmax must hold classes in [0, {num_classes}), got values in [{low}, {high}]"
        )


def _check_class_ids(num_classes: int, votes_from: int, unprojected: int) -> None:
    """Raise ValueError, naming the argument, unless there are classes and both ids are among them."""
    if not is_int(num_classes) or num_classes < 2:
        raise ProjectionError(f"num_classes must be an integer >= 2, got {num_classes!r}")
    for name, value in (("votes_from", votes_from), ("unprojected", unprojected)):
        if not is_int(value) or not 0 <= value < num_classes:
            raise ProjectionError(
                f"{name} must be a class id in 0..{num_classes - 1}, got {value!r}"
            )
