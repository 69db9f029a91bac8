"""Which exact form of a token mixer runs: by rule on the CPU, by one measurement on CUDA.

A mixer offers its forms as candidates, named and ready to run on the layer's inputs, and names the
device's default: the tiled forms on the CPU, where `benchmarks/bench_models.py` shows them several
times faster than the N x N forms; the N x N forms on CUDA, as before any measurement. Where the
device type is not in `MEASURED` the default runs. On CUDA the first call for an (operation, device,
dtype, input shapes) key runs every candidate: one that raises (a kernel that does not compile) or
whose output differs from the default's by more than float rounding (`tolerance`) is set aside,
the others are timed, and the fastest is cached and logged at INFO. Every later call reuses the
choice; under `torch.compile` tracing the cached choice or the default runs, unmeasured. Under
`torch.export` (the ONNX export) the default runs without a look-up, whose key holds the input's
shape and would fix the exported graph's batch size.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping

import torch

log = logging.getLogger(__name__)

#: Device types whose forms are chosen by measurement; elsewhere the first candidate runs.
MEASURED = ("cuda",)

#: Timed runs per candidate (after one warm-up run).
REPEAT = 3

_choices: dict[tuple[object, ...], str] = {}


def run(
    operation: str,
    candidates: Mapping[str, Callable[[], torch.Tensor]],
    default: str,
    q: torch.Tensor,
    v: torch.Tensor,
) -> torch.Tensor:
    """Output of the chosen candidate for queries `q` and values `v` (which key the choice)."""
    return candidates[choose(operation, candidates, default, q, v)]()


def choose(
    operation: str,
    candidates: Mapping[str, Callable[[], torch.Tensor]],
    default: str,
    q: torch.Tensor,
    v: torch.Tensor,
) -> str:
    """Name of the candidate that runs `operation` on inputs shaped like `q` and `v`."""
    if torch.compiler.is_exporting():
        return default
    key = (operation, q.device, q.dtype, tuple(q.shape), v.shape[-1], tuple(candidates))
    choice = _choices.get(key)
    if choice is not None:
        return choice
    if q.device.type not in MEASURED or len(candidates) == 1 or torch.compiler.is_compiling():
        return default
    with torch.no_grad():
        choice, report = _measure(candidates, default, q.device, q.dtype)
    log.info(
        "token mixing %s on %s, %s, queries %s, value width %d: %s (%s)",
        operation,
        q.device,
        str(q.dtype).removeprefix("torch."),
        "x".join(map(str, q.shape)),
        v.shape[-1],
        choice,
        report,
    )
    _choices[key] = choice
    return choice


def choices() -> dict[tuple[object, ...], str]:
    """A snapshot of the choices made so far, by key."""
    return dict(_choices)


def forget() -> None:
    """Drop every choice, so that the next call measures again."""
    _choices.clear()


def tolerance(dtype: torch.dtype) -> float:
    """Largest difference between two exact forms, relative to the output's largest magnitude:
    16 units of float rounding in `dtype`, and at least 1e-4 for the long sums of float32."""
    return max(16 * torch.finfo(dtype).eps, 1e-4)


def _measure(
    candidates: Mapping[str, Callable[[], torch.Tensor]],
    default: str,
    device: torch.device,
    dtype: torch.dtype,
) -> tuple[str, str]:
    """The fastest candidate that runs and agrees with `default`, and a line of what was seen."""
    reference = candidates[default]().float()
    scale = reference.abs().max().clamp(min=1)
    seen, times = [], {}
    for name, fn in candidates.items():
        try:
            out = fn()
        except Exception as err:  # a kernel that does not build here is set aside, not fatal
            seen.append(f"{name} failed: {type(err).__name__}")
            continue
        error = ((out.float() - reference).abs().max() / scale).item()
        if not error <= tolerance(dtype):
            seen.append(f"{name} differs by {error:.1e}")
            continue
        times[name] = _time(fn, device)
        seen.append(f"{name} {times[name] * 1000:.2f} ms")
    return min(times, key=times.__getitem__, default=default), ", ".join(seen)


def _time(fn: Callable[[], torch.Tensor], device: torch.device) -> float:
    """Mean seconds of `REPEAT` runs of `fn` after a warm-up (synchronised on CUDA)."""
    fn()
    _synchronize(device)
    start = time.perf_counter()
    for _ in range(REPEAT):
        fn()
    _synchronize(device)
    return (time.perf_counter() - start) / REPEAT


def _synchronize(device: torch.device) -> None:
    """Wait for `device`'s queued work (CUDA only)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
