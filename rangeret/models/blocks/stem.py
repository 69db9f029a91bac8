"""Range Embedding Modules: per-pixel features from the 5-channel range image (`rem`).

- `ConvREM`: the thesis's REM (section 3.2.1, Eq. 3.2, Fig. 3.7-3.8): three [Conv 3x3 ->
  InstanceNorm (affine) -> GELU] layers, 5 -> dim/4 -> dim/2 -> dim (5-32-64-128).
- `LinearREM`: the per-pixel MLP REM of the ablation (section 4.4 "Range Embedding Module",
  Table 5.8 first row): three [Linear -> LayerNorm -> GELU] layers, 5 -> dim/2 -> dim -> dim.
- `ContextStem`: the released network's stem: three residual context blocks and one residual
  block with dilated convolutions, LeakyReLU and BatchNorm (keys `rem.conv_block.{0..3}`).

All map (B, 5, H, W) to (B, dim, H, W). In eval mode without autograd the released stem applies
LeakyReLU and BatchNorm in place of each convolution's output (`act_norm`).
"""

from __future__ import annotations

from itertools import pairwise

import torch
import torch.nn.functional as F
from torch import nn

LEAKY_SLOPE = 0.01


class ConvBlock(nn.Module):
    """O = GELU(InstanceNorm(Conv3x3(X))) (thesis Eq. 3.2)."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.norm = nn.InstanceNorm2d(out_channels, affine=True)
        self.act = nn.GELU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, H, W)."""
        return self.act(self.norm(self.conv(x)))


class ConvREM(nn.Module):
    """Three `ConvBlock`s, in_channels -> dim/4 -> dim/2 -> dim (thesis Fig. 3.8)."""

    def __init__(self, in_channels: int, dim: int) -> None:
        super().__init__()
        widths = (in_channels, dim // 4, dim // 2, dim)
        self.blocks = nn.Sequential(*(ConvBlock(a, b) for a, b in pairwise(widths)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 5, H, W) -> (B, dim, H, W)."""
        return self.blocks(x)


class LinearBlock(nn.Module):
    """GELU(LayerNorm(Linear(x))) on the channels of every pixel."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.linear = nn.Linear(in_channels, out_channels)
        self.norm = nn.LayerNorm(out_channels)
        self.act = nn.GELU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(..., C_in) -> (..., C_out)."""
        return self.act(self.norm(self.linear(x)))


class LinearREM(nn.Module):
    """Three `LinearBlock`s per pixel, in_channels -> dim/2 -> dim -> dim."""

    def __init__(self, in_channels: int, dim: int) -> None:
        super().__init__()
        widths = (in_channels, dim // 2, dim, dim)
        self.blocks = nn.Sequential(*(LinearBlock(a, b) for a, b in pairwise(widths)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 5, H, W) -> (B, dim, H, W) (laid out channels-last in memory)."""
        return self.blocks(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


def act_norm(x: torch.Tensor, bn: nn.BatchNorm2d) -> torch.Tensor:
    """BN(LeakyReLU(x)) for a fresh convolution output x, computed in place of x in eval mode.

    At 64 x 1024 every feature map is 33.5 MB, more than the allocator recycles, so each new one
    costs page faults; in eval mode the BatchNorm is the affine map x * scale + shift.
    """
    x = F.leaky_relu_(x, LEAKY_SLOPE)
    if bn.training or (torch.is_grad_enabled() and x.requires_grad):
        return bn(x)
    scale = bn.weight * torch.rsqrt(bn.running_var + bn.eps)
    shift = bn.bias - bn.running_mean * scale
    return torch.addcmul(shift[:, None, None], x, scale[:, None, None], out=x)


class ResidualContextBlock(nn.Module):
    """s = LReLU(Conv1x1(x)); a = BN(LReLU(Conv3x3(s))); b = BN(LReLU(Conv3x3 dil 2(a))); s + b."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 1)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv3 = nn.Conv2d(out_channels, out_channels, 3, padding=2, dilation=2)
        self.bn2 = nn.BatchNorm2d(out_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, H, W)."""
        shortcut = F.leaky_relu_(self.conv1(x), LEAKY_SLOPE)
        a = act_norm(self.conv2(shortcut), self.bn1)
        return act_norm(self.conv3(a), self.bn2).add_(shortcut)


class ResidualBlock(nn.Module):
    """Shortcut LReLU(Conv1x1(x)) plus BN(LReLU(Conv1x1(cat(a1, a2, a3)))) of three chained
    BN(LReLU(conv)) features of x: 3x3, 3x3 dilation 2, and 2x2 dilation 2.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 1)
        self.conv2 = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv3 = nn.Conv2d(out_channels, out_channels, 3, padding=2, dilation=2)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.conv4 = nn.Conv2d(out_channels, out_channels, 2, padding=1, dilation=2)
        self.bn3 = nn.BatchNorm2d(out_channels)
        self.conv5 = nn.Conv2d(3 * out_channels, out_channels, 1)
        self.bn4 = nn.BatchNorm2d(out_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, H, W)."""
        shortcut = F.leaky_relu_(self.conv1(x), LEAKY_SLOPE)
        a1 = act_norm(self.conv2(x), self.bn1)
        a2 = act_norm(self.conv3(a1), self.bn2)
        a3 = act_norm(self.conv4(a2), self.bn3)
        return act_norm(self.conv5(torch.cat((a1, a2, a3), dim=1)), self.bn4).add_(shortcut)


class ContextStem(nn.Module):
    """The released stem: residual context blocks in -> dim -> dim -> dim, then a residual block."""

    def __init__(self, in_channels: int, dim: int) -> None:
        super().__init__()
        self.conv_block = nn.Sequential(
            ResidualContextBlock(in_channels, dim),
            ResidualContextBlock(dim, dim),
            ResidualContextBlock(dim, dim),
            ResidualBlock(dim, dim),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 5, H, W) -> (B, dim, H, W)."""
        return self.conv_block(x)


def build_stem(family: str, rem: str, in_channels: int, dim: int) -> nn.Module:
    """The REM of a network family: `rem="linear"` is the MLP ablation, `"conv"` the family's own."""
    if rem == "linear":
        return LinearREM(in_channels, dim)
    if family == "cir":
        return ContextStem(in_channels, dim)
    return ConvREM(in_channels, dim)
