"""Semantic Head (thesis section 3.2.3, Eq. 3.15, Fig. 3.14): tokens back to per-pixel class logits."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class SemanticHead(nn.Module):
    """Tokens -> (Hp, Wp) map -> bilinear resize to (H, W) -> (+ REM features) -> per-pixel MLP.

    The MLP is Linear(dim, hidden) -> norm -> GELU -> Linear(hidden, classes); the norm is a
    LayerNorm in the thesis and a BatchNorm2d in the released network (`norm="batch"`).
    """

    def __init__(self, dim: int, hidden: int, num_classes: int, norm: str) -> None:
        super().__init__()
        self.mlp1 = nn.Linear(dim, hidden)
        self.norm = nn.BatchNorm2d(hidden) if norm == "batch" else nn.LayerNorm(hidden)
        self.act = nn.GELU()
        self.mlp2 = nn.Linear(hidden, num_classes)

    def forward(
        self,
        tokens: torch.Tensor,
        grid: tuple[int, int],
        size: tuple[int, int],
        residual: torch.Tensor | None,
    ) -> torch.Tensor:
        """(B, Hp*Wp, dim) tokens and optional (B, dim, H, W) REM features -> (B, classes, H, W)."""
        b, _, c = tokens.shape
        x = tokens.reshape(b, grid[0], grid[1], c).permute(0, 3, 1, 2)
        x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        if residual is not None:
            x = x.add_(residual)
        x = self.mlp1(x.permute(0, 2, 3, 1))
        if isinstance(self.norm, nn.BatchNorm2d):
            x = self.norm(x.permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
        else:
            x = self.norm(x)
        return self.mlp2(self.act(x)).permute(0, 3, 1, 2).contiguous()
