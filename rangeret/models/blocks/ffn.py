"""Feed-forward sub-layers of the RetNet blocks (thesis Eq. 3.14, Fig. 3.13, and the released variant)."""

from __future__ import annotations

import torch
from torch import nn


class FeedForward(nn.Module):
    """FFN(X) = GELU(X W_1 + b_1) W_2 + b_2, dim -> ratio * dim -> dim (thesis Eq. 3.14)."""

    def __init__(self, dim: int, ratio: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, ratio * dim)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(ratio * dim, dim)

    def forward(self, x: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
        """(B, N, dim) -> (B, N, dim); token-wise, so the grid is not needed."""
        return self.fc2(self.act(self.fc1(x)))


class DepthwiseConv(nn.Module):
    """Depthwise 3x3 convolution (zero padding 1) of tokens laid back on their (Hp, Wp) grid."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.dwconv = nn.Conv2d(channels, channels, 3, padding=1, groups=channels)

    def forward(self, x: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
        """(B, N, C) -> (B, N, C)."""
        b, _, c = x.shape
        image = x.transpose(1, 2).reshape(b, c, grid[0], grid[1])
        return self.dwconv(image).flatten(2).transpose(1, 2)


class ConvFeedForward(nn.Module):
    """Released FFN: fc1 -> depthwise 3x3 conv on the token grid -> GELU -> fc2, all with biases."""

    def __init__(self, dim: int, ratio: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, ratio * dim)
        self.dwconv = DepthwiseConv(ratio * dim)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(ratio * dim, dim)

    def forward(self, x: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
        """(B, N, dim) -> (B, N, dim)."""
        return self.fc2(self.act(self.dwconv(self.fc1(x), grid)))
