"""Rotary position angles of queries and keys (the Theta of thesis Eq. 3.8, RetNet's xPos rotation)."""

from __future__ import annotations

import torch


def rotary_angles(num_tokens: int, key_dim: int, dtype: torch.dtype) -> torch.Tensor:
    """(2, N, key_dim) cos and sin of position n times angle_j = 1 / 10000^(j / (key_dim/2 - 1)).

    Each angle serves two neighbouring channels; the position is the flat token index. Computed in
    `dtype` (float32 reproduces the released network's arithmetic exactly).
    """
    angle = 1.0 / (10000 ** torch.linspace(0, 1, key_dim // 2, dtype=dtype))
    angle = angle.repeat_interleave(2)
    phase = torch.arange(num_tokens, dtype=dtype)[:, None] * angle[None, :]
    return torch.stack((torch.cos(phase), torch.sin(phase)))


def rotate_pairs(x: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """Rotate channel pairs (x0, x1) -> (x0 cos - x1 sin, x1 cos + x0 sin) of (..., N, key_dim)."""
    cos, sin = angles[0], angles[1]
    pairs = x.unflatten(-1, (-1, 2))
    swapped = torch.stack((-pairs[..., 1], pairs[..., 0]), dim=-1).flatten(-2)
    return x * cos + swapped * sin
