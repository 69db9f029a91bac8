"""Numeric precision of a network's forward pass: fp32, fp16 or bf16, chosen per run.

`auto` is fp16 on CUDA and fp32 on the CPU. fp16 and bf16 run under `torch.autocast` (weights
stay fp32; logits come back as fp32); fp32 on CUDA turns TF32 off for the pass, so fp32 means
fp32 on every device. The same weights, precision, batch size and device type give the same
labels. With the onnxruntime backend only fp32 runs (`rangeret.inference.runtime.backends` says why). The module
imports torch only when a pass runs, so option parsing stays light.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING

from rangeret.inference.runtime.backends import RuntimeChoiceError, check_backend

if TYPE_CHECKING:
    import torch

#: The values of --precision.
PRECISIONS = ("auto", "fp32", "fp16", "bf16")


def resolve_precision(name: str, device: torch.device, backend: str = "torch") -> str:
    """The precision a run uses on `device` with `backend`: `auto` becomes fp16 on CUDA and fp32
    elsewhere with torch, and fp32 with onnxruntime (which refuses fp16 and bf16)."""
    if name not in PRECISIONS:
        raise RuntimeChoiceError(
            f"--precision must be one of {', '.join(PRECISIONS)}, got {name!r}"
        )
    check_backend(backend, name)
    if name == "auto":
        return "fp16" if device.type == "cuda" and backend == "torch" else "fp32"
    return name


@contextlib.contextmanager
def forward_precision(precision: str, device: torch.device) -> Iterator[None]:
    """Run the body's forward passes at `precision` (fp32, fp16 or bf16) on `device`."""
    import torch

    if precision == "fp32":
        if device.type != "cuda":
            yield
            return
        matmul, cudnn = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
        try:
            yield
        finally:
            torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = matmul, cudnn
        return
    dtype = {"fp16": torch.float16, "bf16": torch.bfloat16}[precision]
    with torch.autocast(device.type, dtype=dtype):
        yield
