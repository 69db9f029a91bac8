"""Helpers shared by the benchmarks: timing with medians and the real scan's location."""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"
REAL_SCAN = SHARED / "data" / "semantickitti-scan" / "000000.bin"
REAL_LABELS = SHARED / "data" / "semantickitti-scan" / "000000.label"

sys.path.insert(
    0, str(REPO / "tests")
)  # the slow, direct reference formulations live with the tests


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
    """Exit with a message when the real scan is not beside the project."""
    if not REAL_SCAN.exists():
        sys.exit(f"{REAL_SCAN} is missing: the benchmarks need ../shared beside the project")
