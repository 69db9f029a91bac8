"""The RangeRet network (thesis Fig. 3.6): REM -> VEM -> RetNet -> Semantic Head, with the residual."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from rangeret.models.blocks.backbone import RetNetBackbone
from rangeret.models.blocks.embedding import PatchEmbedding
from rangeret.models.blocks.head import SemanticHead
from rangeret.models.blocks.stem import build_stem
from rangeret.models.configs import ModelConfig, resolve_config
from rangeret.models.weights.checkpoint_info import CheckpointInfo


class RangeRet(nn.Module):
    """(B, 5, H, W) normalised range image -> (B, num_classes, H, W) logits.

    `config` says which network it is; `config.height`/`width` is the resolution the weights are
    meant for, but any input whose patch grid is at least 1 x 1 runs. After `load_checkpoint`,
    `checkpoint_info` describes the file the weights came from (None otherwise).
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.checkpoint_info: CheckpointInfo | None = None
        self.rem = build_stem(config.family, config.rem, config.in_channels, config.dim)
        self.viembed = PatchEmbedding(config.dim, config.patch_size, config.stride)
        self.backbone = RetNetBackbone(config)
        norm = "batch" if config.family == "cir" else "layer"
        self.head = SemanticHead(config.dim, config.head_dim, config.num_classes, norm)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits (B, C, H, W) of a (B, in_channels, H, W) batch."""
        if x.dim() != 4 or x.shape[1] != self.config.in_channels:
            raise ValueError(
                f"{self.config.name} takes (B, {self.config.in_channels}, H, W) input, got {tuple(x.shape)}"
            )
        features = self.rem(x.contiguous(memory_format=torch.channels_last))
        tokens, grid = self.viembed(features)
        tokens = self.backbone(tokens, grid)
        residual = features if self.config.residual else None
        return self.head(tokens, grid, (x.shape[-2], x.shape[-1]), residual)


def build_model(
    name: str, height: int = 64, width: int = 1024, num_classes: int = 20, **overrides: Any
) -> RangeRet:
    """A freshly initialised network `name` (see `list_models`) for (B, 5, height, width) input."""
    return RangeRet(resolve_config(name, height, width, num_classes, **overrides))
