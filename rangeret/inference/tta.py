"""Test-time augmentation: the mirrored and azimuth-rotated views of a batch of range images."""

from __future__ import annotations

import numpy as np
import torch

from rangeret.dataset.projection import ProjectionConfig


def transformed_view(
    batch: torch.Tensor, flipped: bool, shift: int, config: ProjectionConfig
) -> torch.Tensor:
    """A view of normalised range images as if the scene were mirrored (y -> -y) and/or rotated.

    Mirroring flips the columns; rotating by `shift` columns rolls them. The x and y channels are
    transformed with the scene, so the view looks like a real scan to the network.
    """
    if not flipped and not shift:
        return batch
    out = batch.clone()
    mask = (batch != 0).any(dim=1, keepdim=True)
    means = torch.tensor(config.means, dtype=batch.dtype, device=batch.device)
    stds = torch.tensor(config.stds, dtype=batch.dtype, device=batch.device)
    x = batch[:, 1] * stds[1] + means[1]
    y = batch[:, 2] * stds[2] + means[2]
    if flipped:
        y = -y
        out = torch.flip(out, dims=[-1])
        x, y, mask = torch.flip(x, dims=[-1]), torch.flip(y, dims=[-1]), torch.flip(mask, dims=[-1])
    if shift:
        # Column u holds yaw = -atan2(y, x); moving content right by `shift` columns is a rotation
        # of the points by -2 pi shift / W about z.
        angle = -2 * np.pi * shift / batch.shape[-1]
        cos, sin = float(np.cos(angle)), float(np.sin(angle))
        x, y = cos * x - sin * y, sin * x + cos * y
        out = torch.roll(out, shift, dims=-1)
        x, y, mask = (torch.roll(t, shift, dims=-1) for t in (x, y, mask))
    out[:, 1] = torch.where(mask[:, 0], (x - means[1]) / stds[1], 0)
    out[:, 2] = torch.where(mask[:, 0], (y - means[2]) / stds[2], 0)
    return out
