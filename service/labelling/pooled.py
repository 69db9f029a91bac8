"""Single scans of several models labelled in the gateway's own process.

Each loaded model is a `ModelRuntime`: its predictor (shared with the gateway's in-process jobs)
behind its own `ScanBatcher`, so batches stay per model; its panoptic requests (`panoptic=true`)
gather behind a second batcher, made on the first one, whose worker shares the network and
clusters the scans' thing points into objects. `PooledLabeller` takes a request's
model from the `ModelPool`, which keeps at most `--max-loaded` of them: the model is held while
its scan is labelled, loaded first where it is not (in a worker thread), and a model that cannot
be loaded because every slot is held by running jobs, or whose checkpoint changed since the
gateway started (replaced, truncated, gone: logged once), is a `BackendError` (503). The
labeller keeps no model of its own: what the pool evicts is gone once its last request ends.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from rangeret.exceptions import RangeRetError
from rangeret.inference.loaded_weights import RefusalLog
from rangeret.inference.predictor import Predictor
from rangeret.inference.results import ScanPrediction
from rangeret.inference.scan_worker import ScanRequest
from rangeret.inference.settings import ClusterSettings
from service.labelling.batching import ScanBatcher
from service.labelling.errors import BackendError
from service.labelling.panoptic import clustered_worker
from service.models.pool import ModelPool, PoolFull

log = logging.getLogger(__name__)


@dataclass
class ModelRuntime:
    """One loaded model: the batcher of its single scans, its predictor (None in tests whose
    worker needs no network), how it finds objects, and the batcher of its panoptic scans once
    one was asked for."""

    batcher: ScanBatcher
    predictor: Predictor | None = None
    clustering: ClusterSettings = field(default_factory=ClusterSettings)
    objects: ScanBatcher | None = None

    def batcher_for(self, panoptic: bool) -> ScanBatcher:
        """The batcher of plain scans, or of panoptic ones (made on first use, with the same
        batch size and wait as the plain one)."""
        if not panoptic:
            return self.batcher
        if self.objects is None:
            worker = clustered_worker(self.batcher.worker, self.clustering)
            self.objects = ScanBatcher(worker, self.batcher.batch_size, self.batcher.max_wait)
        return self.objects

    def batchers(self) -> list[ScanBatcher]:
        """Every batcher of the model."""
        return [self.batcher] if self.objects is None else [self.batcher, self.objects]


class PooledLabeller:
    """Labels single scans with the loaded model each request names, loading it on first use."""

    backend = "local"

    def __init__(self, pool: ModelPool[ModelRuntime]) -> None:
        self.pool = pool
        self._on_batch: Callable[[int, float], None] | None = None
        self._serving = False
        self._refusals = RefusalLog(log)

    async def start(self, on_batch: Callable[[int, float], None] | None = None) -> None:
        """Take scans from now on; `on_batch(size, seconds)` is called after each batch of any
        model."""
        self._on_batch = on_batch
        self._serving = True

    async def stop(self) -> None:
        """Stop every loaded model's batcher; requests still waiting fail."""
        self._serving = False
        for _, runtime in self.pool.items():
            for batcher in runtime.batchers():
                await batcher.stop()

    async def label_points(
        self,
        points: np.ndarray,
        knn: bool = True,
        confidence: bool = False,
        panoptic: bool = False,
        *,
        model: str,
    ) -> ScanPrediction:
        """One scan labelled by `model` within a batch of that model's scans (with `panoptic`,
        of its panoptic scans: with the scan's objects)."""
        if not self._serving:
            raise BackendError("the gateway is not taking scans now (starting or shutting down)")
        try:
            runtime = await asyncio.to_thread(self.pool.acquire, model)
        except PoolFull as exc:
            raise BackendError(str(exc)) from exc
        except RangeRetError as exc:  # its checkpoint changed or went since the start
            reason = self._refusals.note(model, exc)
            raise BackendError(f"model {model} cannot be loaded again: {reason}") from exc
        try:
            batcher = runtime.batcher_for(panoptic)
            if not batcher.accepting:  # loaded (or asked for objects) since the labeller started
                await batcher.start(self._on_batch)
            return await batcher.label_request(ScanRequest(points, knn, confidence))
        finally:
            self.pool.release(model)

    def depth(self) -> int:
        """Requests waiting plus batches in the networks, over the loaded models."""
        return sum(
            batcher.depth() for _, runtime in self.pool.items() for batcher in runtime.batchers()
        )

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
