"""The device a run asks for, resolved to the one torch has."""

from __future__ import annotations

import torch

from rangeret.inference.runtime.backends import RuntimeChoiceError


def select_device(device: str | torch.device = "auto") -> torch.device:
    """`auto` picks CUDA when torch sees a GPU and the CPU otherwise; `cuda` without one is an error."""
    if str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeChoiceError("--device cuda was asked for but torch sees no CUDA device")
    return dev
