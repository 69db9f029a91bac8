"""Gateway apps built in the test process: a catalog of one model, and a scan worker (real or
fake) behind the gateway's pooled labeller, as `rangeret serve` builds them."""

from __future__ import annotations

from rangeret.dataset.profiles import DatasetProfile
from rangeret.inference.spec import InferenceSpec
from service.labelling.batching import ScanBatcher
from service.labelling.pooled import ModelRuntime, PooledLabeller
from service.models.catalog import ModelCatalog, ModelEntry
from service.models.pool import ModelPool


def one_model(
    profile: DatasetProfile,
    checkpoint_sha256: str | None = None,
    network: str | None = None,
    name: str = "default",
) -> ModelCatalog:
    """The catalog of one model `name` running with `profile`."""
    entry = ModelEntry(name, InferenceSpec(), profile, checkpoint_sha256, network)
    return ModelCatalog.one(entry)


def pooled(worker: object, name: str = "default") -> PooledLabeller:
    """A pooled labeller whose one model is `worker` (a `ScanWorker` or a fake one), loaded
    before the gateway starts as `rangeret serve` loads its default model."""
    runtime = ModelRuntime(ScanBatcher(worker), getattr(worker, "predictor", None))
    pool: ModelPool[ModelRuntime] = ModelPool([name], lambda _: runtime)
    pool.acquire(name)
    pool.release(name)
    return PooledLabeller(pool)
