"""A long-lived pool of model actors that labels single scans, in batches, for the gateway.

`ScanPool` keeps `actors` Ray actors with the network loaded and warmed up (one GPU each when
asked, CPU otherwise) and sends each batch to the least busy one; Ray restarts an actor that dies
and retries its calls, so a crash costs a delay, not a request. On a GPU cluster the gateway's jobs
run on these actors too (`service.jobs.RayExecutor`), so the pool may hold every GPU and jobs
still run. `LocalScanPool` has the same interface and runs the network in this process, for a
gateway without a cluster.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rangeret.inference import PredictorSpec
from rangeret.projection import Projection
from workers.pipeline import GPU_ACTOR_CPUS, warm_up
from workers.pipeline import label_batch as label_record

log = logging.getLogger(__name__)


@dataclass
class LabelledScan:
    """One scan labelled by a worker: raw labels (uint32, one per point) and, when asked, each
    point's confidence in its label (float32)."""

    labels: np.ndarray
    confidence: np.ndarray | None = None


class ScanWorker:
    """The state of one model actor: its predictor as the spec builds it, and one without kNN.

    `spec_predictor` refines with kNN only when the spec asks for it; `knn=False` requests get
    `without_knn`, which shares its network. The network is warmed up before the worker answers.
    """

    def __init__(self, spec: PredictorSpec, cpus: float = 1.0) -> None:
        import torch

        torch.set_num_threads(max(1, math.ceil(cpus)))
        self.spec_predictor = spec.build()
        knn = self.spec_predictor.knn
        self.without_knn = self.spec_predictor.with_knn(None)
        if knn is None:
            self.spec_predictor = self.without_knn
        self.warm_up_seconds = warm_up(self.spec_predictor)

    def info(self) -> dict:
        """Who this worker is: process, device and model, for health checks."""
        return {"pid": os.getpid(), **self.spec_predictor.describe()}

    def predict(
        self, scans: Sequence[np.ndarray], knn: bool = True, confidence: bool = False
    ) -> list[LabelledScan | str]:
        """Each scan of a batch of the profile's point records labelled (with its points'
        confidences when asked); a scan that cannot be projected (a laser id off the image) gets
        the reason instead, so it never fails the other scans of its batch."""
        predictor = self.spec_predictor if knn else self.without_knn
        projections: list[Projection] = []
        rejected: dict[int, str] = {}
        for i, scan in enumerate(scans):
            try:
                projections.append(predictor.project(scan))
            except ValueError as exc:
                rejected[i] = str(exc)
        done = iter(
            [
                LabelledScan(r.labels, r.confidence)
                for r in predictor.finish_batch(projections, with_confidence=confidence)
            ]
            if projections
            else []
        )
        return [rejected[i] if i in rejected else next(done) for i in range(len(scans))]

    def label_batch(self, encoded: bytes) -> bytes:
        """A job's batch (an encoded `workers.stages.BatchRecord`), labelled as the pipeline's
        own model actors label it, with the spec's predictor."""
        return label_record(self.spec_predictor, encoded)


class ScanPool:
    """Model actors on the connected Ray cluster, serving batches of scans.

    By default one actor per GPU of the cluster (1 on CPU clusters). GPU actors reserve one GPU
    each whatever device the spec names, so a spec with `device="cpu"` runs on logical GPUs.
    """

    def __init__(
        self,
        spec: PredictorSpec,
        actors: int | None = None,
        use_gpu: bool | None = None,
        actor_cpus: float = 1.0,
    ) -> None:
        import ray

        gpus = int(ray.cluster_resources().get("GPU", 0))
        use_gpu = gpus > 0 if use_gpu is None else use_gpu
        if use_gpu and not gpus:
            raise ValueError("GPU actors were asked for but the Ray cluster has no GPU")
        count = actors or (gpus if use_gpu else 1)
        if use_gpu:
            actor_cpus = GPU_ACTOR_CPUS
        self.use_gpu = use_gpu
        resources = {"num_gpus": 1, "num_cpus": actor_cpus} if use_gpu else {"num_cpus": actor_cpus}
        remote = ray.remote(max_restarts=-1, max_task_retries=-1, **resources)(ScanWorker)
        self.actors = [remote.remote(spec, actor_cpus) for _ in range(count)]
        self._busy = [0] * count
        self._lock = threading.Lock()
        self.backend = "ray"

    def wait_ready(self, timeout: float | None = None) -> list[dict]:
        """Block until every actor has loaded its network; return their descriptions."""
        import ray

        return ray.get([a.info.remote() for a in self.actors], timeout=timeout)

    def _pick(self) -> int:
        with self._lock:
            index = min(range(len(self.actors)), key=self._busy.__getitem__)
            self._busy[index] += 1
            return index

    def _release(self, index: int) -> None:
        with self._lock:
            self._busy[index] -= 1

    async def predict_async(
        self, scans: Sequence[np.ndarray], knn: bool = True, confidence: bool = False
    ) -> list[LabelledScan | str]:
        """Labels (or the reason a scan is refused) for a batch of scans from the least busy
        actor, awaited without blocking the loop."""
        index = self._pick()
        try:
            return await self.actors[index].predict.remote(list(scans), knn, confidence)
        finally:
            self._release(index)

    def queue_depth(self) -> int:
        """Batches sent to the actors and not answered yet."""
        with self._lock:
            return sum(self._busy)

    def health(self) -> dict:
        """Actors and their state, for `/healthz`."""
        import ray

        try:
            infos = ray.get([a.info.remote() for a in self.actors], timeout=10)
            return {"backend": "ray", "ok": True, "actors": infos}
        except Exception as exc:  # a health check reports, it does not raise
            return {"backend": "ray", "ok": False, "error": str(exc)}

    def shutdown(self) -> None:
        """Stop the actors."""
        import ray

        for actor in self.actors:
            ray.kill(actor)
        self.actors = []


class LocalScanPool:
    """The same interface as `ScanPool`, running the network in this process (one batch at a time)."""

    def __init__(self, spec: PredictorSpec) -> None:
        self.worker = ScanWorker(spec, cpus=float(os.cpu_count() or 1))
        self._lock = threading.Lock()
        self._waiting = 0
        self.backend = "local"

    def wait_ready(self, timeout: float | None = None) -> list[dict]:
        return [self.worker.info()]

    def predict(
        self, scans: Sequence[np.ndarray], knn: bool = True, confidence: bool = False
    ) -> list[LabelledScan | str]:
        with self._lock:
            return self.worker.predict(scans, knn, confidence)

    async def predict_async(
        self, scans: Sequence[np.ndarray], knn: bool = True, confidence: bool = False
    ) -> list[LabelledScan | str]:
        self._waiting += 1
        try:
            return await asyncio.to_thread(self.predict, scans, knn, confidence)
        finally:
            self._waiting -= 1

    def queue_depth(self) -> int:
        return self._waiting

    def health(self) -> dict:
        return {"backend": "local", "ok": True, "actors": [self.worker.info()]}

    def shutdown(self) -> None:
        """Nothing to stop: the network lives in this process."""
