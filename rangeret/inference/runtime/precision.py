"""Numeric precision of a network's forward pass: fp32, fp16 or bf16, chosen per run.

`auto` picks bf16 where the hardware multiplies bf16 matrices natively, fp32 elsewhere: on the
CPU, bf16 with AMX (`amx_bf16`) or AVX-512 bf16 (`avx512_bf16`), read by
`rangeret.inference.runtime.cpu_features`; on CUDA, bf16 where the device runs it natively
(`torch.cuda.is_bf16_supported` without emulation: compute capability 8.0 and up); with the
onnxruntime backend always fp32. Without native bf16 a CPU emulates it, slower than fp32, so
fp32 is the pick there. `auto_choice` says what auto picks and why, `precision_reason` why a
resolved precision is the one; `resolve_precision` logs the choice as a network is loaded and
keeps its reason for the run's record (`resolved_reason`).

fp16 and bf16 run under `torch.autocast` (weights stay fp32; logits come back as fp32); fp32 on
CUDA turns TF32 off for the pass, so fp32 means fp32 on every device. The same weights,
precision, batch size and device type give the same labels. With the onnxruntime backend only
fp32 runs (`rangeret.inference.runtime.backends` says why). The module imports torch only when a
device is looked at or a pass runs, so option parsing stays light.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING

from rangeret.inference.runtime.backends import RuntimeChoiceError, check_backend
from rangeret.inference.runtime.cpu_features import BF16_FLAGS, FLAG_NAMES, cpu_features

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

#: The values of --precision.
PRECISIONS = ("auto", "fp32", "fp16", "bf16")

#: Why each precision this process resolved is the one, by (precision, device, backend).
_RESOLVED: dict[tuple[str, str, str], str] = {}


@dataclass(frozen=True)
class PrecisionChoice:
    """A precision and why it is the one: `reason` is one clause for logs and answers."""

    precision: str
    reason: str


def auto_choice(device: torch.device | str, backend: str = "torch") -> PrecisionChoice:
    """What `--precision auto` picks on `device` with `backend`, and why (see the module)."""
    if backend != "torch":
        return PrecisionChoice("fp32", f"{backend} runs fp32 only")
    kind = str(device).split(":", 1)[0]
    if kind == "cpu":
        flag = cpu_features().bf16_flag
        if flag is not None:
            return PrecisionChoice("bf16", f"this CPU has {FLAG_NAMES[flag]} ({flag})")
        missing = " nor ".join(f"{FLAG_NAMES[f]} ({f})" for f in BF16_FLAGS)
        return PrecisionChoice("fp32", f"this CPU has neither {missing}, so bf16 is emulated")
    if kind == "cuda":
        return _cuda_choice(device)
    return PrecisionChoice("fp32", f"auto picks bf16 on the CPU and CUDA only, not on {kind}")


def _cuda_choice(device: torch.device | str) -> PrecisionChoice:
    """bf16 on a CUDA device that runs it natively, else fp32."""
    import torch

    if not torch.cuda.is_available():
        return PrecisionChoice("fp32", "torch sees no CUDA device")
    index = torch.device(device).index
    index = torch.cuda.current_device() if index is None else index
    name = torch.cuda.get_device_name(index)
    with torch.cuda.device(index):
        try:
            native = torch.cuda.is_bf16_supported(including_emulation=False)
        except TypeError:  # an older torch counts native support only
            native = torch.cuda.is_bf16_supported()
    if native:
        return PrecisionChoice("bf16", f"{name} runs bf16 natively")
    major, minor = torch.cuda.get_device_capability(index)
    return PrecisionChoice(
        "fp32", f"{name} (compute capability {major}.{minor}) has no native bf16"
    )


def precision_reason(precision: str, device: torch.device | str, backend: str = "torch") -> str:
    """Why a run on `device` with `backend` uses the resolved `precision`: what auto picks here
    when it is that, else that it was asked for and what auto would pick instead."""
    auto = auto_choice(device, backend)
    if precision == auto.precision:
        return f"auto's pick here: {auto.reason}"
    default = " (fp32 is the default)" if precision == "fp32" else ""
    return f"asked for{default}; auto would pick {auto.precision} here: {auto.reason}"


def choose_precision(
    name: str, device: torch.device | str, backend: str = "torch"
) -> PrecisionChoice:
    """The precision `name` (a value of --precision) resolves to on `device` with `backend`, and
    why (`precision_reason`); a `RuntimeChoiceError` for one that is unknown or that `backend`
    cannot run."""
    if name not in PRECISIONS:
        raise RuntimeChoiceError(
            f"--precision must be one of {', '.join(PRECISIONS)}, got {name!r}"
        )
    check_backend(backend, name)
    precision = auto_choice(device, backend).precision if name == "auto" else name
    return PrecisionChoice(precision, precision_reason(precision, device, backend))


def resolve_precision(name: str, device: torch.device, backend: str = "torch") -> str:
    """The precision a run uses on `device` with `backend`: `name`, or for `auto` what
    `auto_choice` picks (fp32 with onnxruntime, which refuses fp16 and bf16). The choice and
    why are logged, as the network is loaded."""
    choice = choose_precision(name, device, backend)
    if name == "auto":
        why = auto_choice(device, backend).reason
        log.info(
            "precision %s on %s, picked by --precision auto: %s", choice.precision, device, why
        )
    else:
        log.info("precision %s on %s: %s", choice.precision, device, choice.reason)
    _RESOLVED[(choice.precision, str(device), backend)] = choice.reason
    return choice.precision


def resolved_reason(precision: str, device: str, backend: str = "torch") -> str | None:
    """Why `precision` is the one on `device` with `backend`, where this process resolved it
    (`resolve_precision`, as a network was loaded here); None where it did not, as in a driver
    whose networks run in other processes, maybe on other machines."""
    return _RESOLVED.get((precision, str(device), backend))


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
