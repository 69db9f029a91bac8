"""onnxruntime sessions on the CPU or on CUDA, with the execution provider each device needs.

The CPU runs `CPUExecutionProvider`; CUDA runs `CUDAExecutionProvider`, which only the
`onnxruntime-gpu` package has: with the CPU-only `onnxruntime` installed, CUDA is refused with one
sentence naming the package. A session takes as many threads as torch does in this process, so a
Ray actor confined to N cores runs onnxruntime on N cores too. onnxruntime is imported only when
a session is made.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from rangeret.extras import require_extra
from rangeret.inference.runtime.backends import RuntimeChoiceError

if TYPE_CHECKING:
    import onnxruntime
    import torch

CPU_PROVIDER = "CPUExecutionProvider"
CUDA_PROVIDER = "CUDAExecutionProvider"


def providers_for(device: torch.device) -> list[Any]:
    """The execution providers of a session on `device`; RuntimeChoiceError (one sentence) when the
    installed onnxruntime cannot run there."""
    ort = _onnxruntime()
    if device.type == "cpu":
        return [CPU_PROVIDER]
    if device.type != "cuda":
        raise RuntimeChoiceError(
            f"--backend onnxruntime runs on the CPU or CUDA, not on {device.type}"
        )
    available = ort.get_available_providers()
    if CUDA_PROVIDER not in available:
        raise RuntimeChoiceError(
            f"--backend onnxruntime on CUDA needs {CUDA_PROVIDER}, which the installed "
            f"onnxruntime {ort.__version__} lacks (it has {', '.join(available)}): install "
            "onnxruntime-gpu in its place, or pass --device cpu"
        )
    return [(CUDA_PROVIDER, {"device_id": device.index or 0}), CPU_PROVIDER]


def make_session(model: bytes | Path, device: torch.device) -> onnxruntime.InferenceSession:
    """A session of an ONNX model (its bytes or its file) on `device`, with torch's thread count."""
    import torch

    ort = _onnxruntime()
    providers = providers_for(device)
    options = ort.SessionOptions()
    options.intra_op_num_threads = torch.get_num_threads()
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only: graph-optimisation notes are not the user's
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, sess_options=options, providers=providers)


def _onnxruntime() -> Any:
    """The onnxruntime module; `MissingExtraError` naming the onnx extra when it is not installed."""
    require_extra("--backend onnxruntime", "onnx")
    import onnxruntime

    return onnxruntime
