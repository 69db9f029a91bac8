"""RetNet backbone (thesis section 3.2.2, Eq. 3.7, Fig. 3.10): L pre-LayerNorm residual blocks.

Y = X + Mixer(LN1(X)); X' = Y + FFN(LN2(Y)). Key names follow the released checkpoints:
`retentions.i`, `ffns.i`, `norms1.i`, `norms2.i`. The backbone owns the `GridCache` its layers share.
"""

from __future__ import annotations

import torch
from torch import nn

from rangeret.models.blocks.decay import GridCache
from rangeret.models.blocks.ffn import ConvFeedForward, FeedForward
from rangeret.models.blocks.retention import (
    CircularRetention,
    MultiScaleRetention,
    SoftmaxAttention,
)
from rangeret.models.configs import ModelConfig


def _mixer(config: ModelConfig) -> nn.Module:
    """The token mixer of one block for `config`."""
    if config.family == "cir":
        return CircularRetention(
            config.dim, config.heads, config.value_factor, config.mixer == "retention"
        )
    if config.mixer == "attention":
        return SoftmaxAttention(config.dim, config.heads, config.value_factor)
    return MultiScaleRetention(config.dim, config.heads, config.value_factor)


class RetNetBackbone(nn.Module):
    """`config.layers` blocks of token mixer and feed-forward network over (B, N, dim) tokens."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        ffn = ConvFeedForward if config.family == "cir" else FeedForward
        self.retentions = nn.ModuleList(_mixer(config) for _ in range(config.layers))
        self.ffns = nn.ModuleList(ffn(config.dim, config.ffn_ratio) for _ in range(config.layers))
        self.norms1 = nn.ModuleList(nn.LayerNorm(config.dim) for _ in range(config.layers))
        self.norms2 = nn.ModuleList(nn.LayerNorm(config.dim) for _ in range(config.layers))
        self.cache = GridCache(config.decay, config.heads, config.key_dim)

    def forward(self, x: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
        """(B, Hp*Wp, dim) -> (B, Hp*Wp, dim)."""
        for mixer, ffn, norm1, norm2 in zip(
            self.retentions, self.ffns, self.norms1, self.norms2, strict=True
        ):
            x = x + mixer(norm1(x), grid, self.cache)
            x = x + ffn(norm2(x), grid)
        return x
