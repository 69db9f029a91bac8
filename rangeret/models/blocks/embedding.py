"""Vision Embedding Module (thesis section 3.2.1, Eq. 3.5 and 3.6, Fig. 3.9): patches to tokens."""

from __future__ import annotations

import torch
from torch import nn


def patch_grid(
    height: int, width: int, patch_size: tuple[int, int], stride: tuple[int, int]
) -> tuple[int, int]:
    """Patch grid (Hp, Wp) = (floor((H - P) / s) + 1, ...) of an image (thesis Eq. 3.6)."""
    return (height - patch_size[0]) // stride[0] + 1, (width - patch_size[1]) // stride[1] + 1


class PatchEmbedding(nn.Module):
    """Conv(P x P, stride s) -> flatten to Hp*Wp tokens -> LayerNorm (the thesis's VEM, `viembed`)."""

    def __init__(self, dim: int, patch_size: tuple[int, int], stride: tuple[int, int]) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.stride = stride
        self.proj = nn.Conv2d(dim, dim, kernel_size=patch_size, stride=stride)
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        """(B, C, H, W) features -> (B, Hp*Wp, C) tokens in row-major grid order, and (Hp, Wp)."""
        require_patch(x, self.patch_size)
        patches = self.proj(x)
        grid = (patches.shape[-2], patches.shape[-1])
        return self.norm(patches.flatten(2).transpose(1, 2)), grid


def require_patch(x: torch.Tensor, patch_size: tuple[int, int]) -> None:
    """ValueError unless the (..., H, W) feature map `x` holds at least one patch."""
    h, w = x.shape[-2:]
    if h < patch_size[0] or w < patch_size[1]:
        raise ValueError(f"a {h}x{w} image holds no {patch_size[0]}x{patch_size[1]} patch")
