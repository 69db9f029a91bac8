"""Single scans labelled in the gateway's own process, when no Serve application is named.

`LocalPool` runs a `workers.scans.ScanWorker` in a worker thread, one batch at a time, and
`LocalLabeller` puts the request batcher (`service.batching.ScanBatcher`) in front of a pool, so
that concurrent requests share network passes of up to `batch_size` scans.
"""

from __future__ import annotations

import asyncio
import os
import threading
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from rangeret.inference.predictor import PredictorSpec
from rangeret.inference.results import ScanPrediction
from service.batching import ScanBackend, ScanBatcher
from workers.scans import ScanWorker


class LocalPool:
    """The network in this process, behind a lock: one batch at a time, off the event loop."""

    def __init__(self, spec: PredictorSpec) -> None:
        self.worker = ScanWorker(spec, cpus=float(os.cpu_count() or 1))
        self._lock = threading.Lock()
        self._waiting = 0

    def _predict(
        self, scans: Sequence[np.ndarray], knn: bool, confidence: bool
    ) -> list[ScanPrediction | str]:
        with self._lock:
            return self.worker.predict(scans, knn, confidence)

    async def predict_async(
        self, scans: Sequence[np.ndarray], knn: bool = True, confidence: bool = False
    ) -> list[ScanPrediction | str]:
        """Each scan of a batch labelled, or the reason it cannot be, in a worker thread."""
        self._waiting += 1
        try:
            return await asyncio.to_thread(self._predict, scans, knn, confidence)
        finally:
            self._waiting -= 1

    def queue_depth(self) -> int:
        """Batches handed to the network and not answered yet."""
        return self._waiting

    def info(self) -> dict:
        """The network this pool runs."""
        return self.worker.info()


class LabellingPool(ScanBackend, Protocol):
    """What `LocalLabeller` needs from a pool (`LocalPool`)."""

    def info(self) -> dict:
        """The network the pool runs."""
        ...


class LocalLabeller:
    """Labels single scans with a pool in this process (a `LocalPool` is built before the
    gateway listens, so its weights are loaded and warmed up by then)."""

    backend = "local"

    def __init__(self, pool: LabellingPool, batch_size: int = 1, max_wait: float = 0.01) -> None:
        self.pool = pool
        self.batch_size = batch_size
        self.max_wait = max_wait
        self.batcher: ScanBatcher | None = None

    async def start(self, on_batch: Callable[[int, float], None] | None = None) -> None:
        """Start the batcher on the serving event loop; `on_batch(size, seconds)` is called
        after each network pass."""
        self.batcher = ScanBatcher(
            self.pool, self.batch_size, self.max_wait, dispatchers=1, on_batch=on_batch
        )
        await self.batcher.start()

    async def stop(self) -> None:
        """Stop the batcher; requests still waiting fail with `BackendError`."""
        if self.batcher is not None:
            await self.batcher.stop()

    async def label(
        self, points: np.ndarray, raw: bytes, knn: bool = True, confidence: bool = False
    ) -> ScanPrediction:
        """One scan labelled within a batch (`raw`, its bytes, is not needed here)."""
        if self.batcher is None:
            raise RuntimeError("the labeller is not started")
        return await self.batcher.label(points, knn, confidence)

    def depth(self) -> int:
        """Requests waiting plus batches in the network."""
        return self.batcher.depth() if self.batcher is not None else 0

    async def health(self) -> dict:
        """The one in-process worker."""
        return {"backend": self.backend, "ok": True, "actors": [self.pool.info()]}
