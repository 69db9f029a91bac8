"""Helpers shared by the benchmarks: timing with medians and the location of their inputs."""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DATA = REPO / "tests" / "data"  # the real scan and test vectors the repository carries
REAL_SCAN = DATA / "semantickitti-scan" / "000000.bin"
REAL_LABELS = DATA / "semantickitti-scan" / "000000.label"
SMALL_VECTORS = DATA / "rangeret-cir-32x256-2block.pt"


def median_time(
    fn: Callable[[], object], repeat: int = 7, number: int = 1, warmup: int = 1
) -> float:
    """Median over `repeat` samples of the mean wall time of `number` calls of `fn()`, in seconds."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        for _ in range(number):
            fn()
        times.append((time.perf_counter() - start) / number)
    return statistics.median(times)


def require_real_scan() -> None:
    """Exit with a message when the real scan is missing from `tests/data`."""
    if not REAL_SCAN.exists():
        sys.exit(f"{REAL_SCAN} is missing: the repository carries it in tests/data")


def small_state_dict() -> dict:
    """The published-layout state_dict of the 32 x 256, 2-block test vectors, upcast to float32."""
    import torch

    state = torch.load(SMALL_VECTORS, weights_only=False)["state_dict"]
    return {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
