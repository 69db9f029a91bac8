"""Single scans of several models labelled in the gateway's own process.

Each loaded model is a `ModelRuntime`: its predictor (shared with the gateway's in-process jobs)
behind its own `ScanBatcher`, so batches stay per model. `PooledLabeller` takes a request's
model from the `ModelPool`, which keeps at most `--max-loaded` of them: the model is held while
its scan is labelled, loaded first where it is not (in a worker thread), and a model that cannot
be loaded because every slot is held by running jobs is a `BackendError` (503, Retry-After).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from rangeret.inference.predictor import Predictor
from rangeret.inference.results import ScanPrediction
from rangeret.inference.scan_worker import ScanRequest
from service.batching import ScanBatcher
from service.labeller_errors import BackendError
from service.model_pool import ModelPool, PoolFull


@dataclass
class ModelRuntime:
    """One loaded model: the batcher of its single scans, and its predictor (None in tests whose
    worker needs no network)."""

    batcher: ScanBatcher
    predictor: Predictor | None = None
    #: Started on the serving event loop at its first scan.
    started: bool = field(default=False, init=False)


class PooledLabeller:
    """Labels single scans with the loaded model each request names, loading it on first use."""

    backend = "local"

    def __init__(self, pool: ModelPool[ModelRuntime]) -> None:
        self.pool = pool
        pool.unload = self.unload
        self._on_batch: Callable[[int, float], None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._starting = asyncio.Lock()

    def unload(self, runtime: ModelRuntime) -> None:
        """The pool's `unload`: stop an evicted model's batcher on the serving loop (nobody holds
        it, so no request waits in it)."""
        if runtime.started and self._loop is not None:
            self._loop.call_soon_threadsafe(asyncio.ensure_future, runtime.batcher.stop())

    async def start(self, on_batch: Callable[[int, float], None] | None = None) -> None:
        """Remember the serving loop and start the batchers of the models loaded already."""
        self._on_batch = on_batch
        self._loop = asyncio.get_running_loop()
        for _, runtime in self.pool.items():
            await self._started(runtime)

    async def stop(self) -> None:
        """Stop every loaded model's batcher; requests still waiting fail."""
        for _, runtime in self.pool.items():
            if runtime.started:
                await runtime.batcher.stop()
                runtime.started = False

    async def _started(self, runtime: ModelRuntime) -> ModelRuntime:
        async with self._starting:
            if not runtime.started:
                await runtime.batcher.start(self._on_batch)
                runtime.started = True
        return runtime

    async def label_points(
        self, points: np.ndarray, knn: bool = True, confidence: bool = False, *, model: str
    ) -> ScanPrediction:
        """One scan labelled by `model` within a batch of that model's scans."""
        try:
            runtime = await asyncio.to_thread(self.pool.acquire, model)
        except PoolFull as exc:
            raise BackendError(str(exc)) from exc
        try:
            await self._started(runtime)
            return await runtime.batcher.label_request(ScanRequest(points, knn, confidence))
        finally:
            self.pool.release(model)

    def depth(self) -> int:
        """Requests waiting plus batches in the networks, over the loaded models."""
        return sum(runtime.batcher.depth() for _, runtime in self.pool.items())

    def loaded(self) -> list[str]:
        """The models loaded now."""
        return self.pool.loaded()

    async def health(self) -> dict:
        """The loaded models' workers, each with the model's name."""
        workers = [
            {**runtime.batcher.worker.info(), "model_id": name}
            for name, runtime in self.pool.items()
        ]
        return {"backend": self.backend, "ok": True, "workers": workers}
