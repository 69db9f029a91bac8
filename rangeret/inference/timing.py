"""Per-stage wall times of a prediction run (read, project, network, refine, write).

A plain record, free of torch, so that the pipeline's CPU stages can carry it between processes
without importing the network's dependencies.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field


@dataclass
class StageTimes:
    """Seconds spent in each stage, and how many scans went through it."""

    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    scans: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    @contextlib.contextmanager
    def stage(self, name: str, scans: int = 1) -> Iterator[None]:
        """Time the body as `scans` scans of stage `name` (safe to use from several threads)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            elapsed = time.perf_counter() - start
            with self._lock:
                self.seconds[name] += elapsed
                self.scans[name] += scans

    def merge(self, other: StageTimes) -> None:
        """Add another record's times and counts."""
        for k, v in other.seconds.items():
            self.seconds[k] += v
        for k, v in other.scans.items():
            self.scans[k] += v

    def __getstate__(self) -> dict:
        """Pickle the times and counts; the lock stays behind (a new one is made on load)."""
        return {"seconds": dict(self.seconds), "scans": dict(self.scans)}

    def __setstate__(self, state: dict) -> None:
        self.seconds = defaultdict(float, state["seconds"])
        self.scans = defaultdict(int, state["scans"])
        self._lock = threading.Lock()

    def per_scan_ms(self) -> dict[str, float]:
        """Mean milliseconds per scan of each stage."""
        return {k: 1e3 * v / max(self.scans[k], 1) for k, v in self.seconds.items()}
