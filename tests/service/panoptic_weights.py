"""Weights for the panoptic gateway tests: a 1-block rangeret-cir with random weights at 32 x 256,
saved alone like a release file, whose labels of the real scan hold several classes, stuff and
things, and dozens of objects."""

from __future__ import annotations

from pathlib import Path

import torch

from rangeret.models import build_model

#: The seed whose random weights label the real scan with several classes and objects.
SEED = 1


def panoptic_weights(folder: Path) -> Path:
    """The random 20-class state_dict (SemanticKITTI's classes) saved under `folder`."""
    net = build_model("rangeret-cir", 32, 256, num_classes=20, layers=1).eval()
    g = torch.Generator().manual_seed(SEED)
    state = {
        k: torch.randn(v.shape, generator=g) * 0.5
        if v.is_floating_point() and not k.endswith("running_var")
        else v
        for k, v in net.state_dict().items()
    }
    path = folder / "cir-panoptic.pt"
    torch.save(state, path)
    return path
