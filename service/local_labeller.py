"""Single scans labelled in the gateway's own process, when no Serve application is named.

`LocalLabeller` puts the request batcher (`service.batching.ScanBatcher`) in front of a
`rangeret.inference.scan_worker.ScanWorker`, so that concurrent requests share network passes of
up to `batch_size` scans. The worker's predictor is the one the gateway's in-process jobs use:
the network runs one pass at a time, so a scan waits at most for the job batch in progress.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rangeret.inference.results import ScanPrediction
from rangeret.inference.scan_worker import ScanRequest, ScanWorker
from service.batching import ScanBatcher


class LocalLabeller:
    """Labels single scans with a scan worker in this process (built before the gateway
    listens, so its weights are loaded and warmed up by then)."""

    backend = "local"

    def __init__(self, worker: ScanWorker, batch_size: int = 1, max_wait: float = 0.01) -> None:
        self.worker = worker
        self.batch_size = batch_size
        self.max_wait = max_wait
        self.batcher: ScanBatcher | None = None

    async def start(self, on_batch: Callable[[int, float], None] | None = None) -> None:
        """Start the batcher on the serving event loop; `on_batch(size, seconds)` is called
        after each network pass."""
        self.batcher = ScanBatcher(self.worker, self.batch_size, self.max_wait, on_batch=on_batch)
        await self.batcher.start()

    async def stop(self) -> None:
        """Stop the batcher; requests still waiting fail with `BackendError`."""
        if self.batcher is not None:
            await self.batcher.stop()

    async def label(
        self, points: np.ndarray, knn: bool = True, confidence: bool = False
    ) -> ScanPrediction:
        """One scan labelled within a batch."""
        if self.batcher is None:
            raise RuntimeError("the labeller is not started")
        return await self.batcher.label(ScanRequest(points, knn, confidence))

    def depth(self) -> int:
        """Requests waiting plus batches in the network."""
        return self.batcher.depth() if self.batcher is not None else 0

    async def health(self) -> dict:
        """The one in-process worker."""
        return {"backend": self.backend, "ok": True, "workers": [self.worker.info()]}
