"""Where a network's forward pass runs: in torch, or in onnxruntime on an export of the same weights.

`torch` runs the loaded network itself at any precision of `rangeret.inference.runtime.precision`. `onnxruntime`
runs an ONNX export of that network (`rangeret.onnx_runtime`), checked against torch when it is
made; projection, kNN refinement and raw ids stay the same code whichever backend runs.

The onnxruntime backend runs fp32 only (`auto` is fp32 there): the export is an fp32 graph,
onnxruntime has no autocast to run it in fp16 or bf16, and a separately converted half-precision
graph would be neither checked against torch nor equal to torch's autocast numerics. Torch-free.
"""

from __future__ import annotations

from rangeret.exceptions import InputError
from rangeret.extras import require_extra

#: The values of --backend.
BACKENDS = ("torch", "onnxruntime")

#: The precisions each backend runs (`auto` resolves to one of them).
BACKEND_PRECISIONS = {
    "torch": ("auto", "fp32", "fp16", "bf16"),
    "onnxruntime": ("auto", "fp32"),
}


class RuntimeChoiceError(InputError, ValueError):
    """A --device, --precision or --backend that is unknown, contradicts another option, or cannot
    run on this machine."""


def check_backend(backend: str, precision: str) -> None:
    """Raise RuntimeChoiceError (one sentence naming the options) for an unknown backend or a
    precision it does not run, and `MissingExtraError` for onnxruntime without the onnx extra."""
    if backend not in BACKENDS:
        raise RuntimeChoiceError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "onnxruntime":
        require_extra("--backend onnxruntime", "onnx")
    if precision not in BACKEND_PRECISIONS[backend]:
        raise RuntimeChoiceError(
            f"--precision {precision} cannot run with --backend {backend}: its exported graph is "
            "fp32 and onnxruntime has no autocast, so it runs fp32 only (pass --precision fp32 "
            "or auto, or --backend torch for fp16 and bf16)"
        )
