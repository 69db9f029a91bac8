"""What the gateway's pool loads: a served model's network, built from its checkpoint, moved to
its device and warmed up behind its own batcher.

`ModelLoader` is the `ModelPool`'s `load`. It keeps what checking each model found (its
`WeightsIdentity`, which the catalog describes) and refuses weights whose checkpoint has changed
since, as a model evicted and used again reads its checkpoint again: bytes of another SHA-256
(replaced, truncated) are refused before they are parsed. At start `ModelLoader.check`
checks every model once: one the pool has room for is loaded into it from that one read of its
checkpoint, any other is identified without building its network, so a gateway builds only the
networks its pool keeps.
"""

from __future__ import annotations

from rangeret.inference.loaded_weights import (
    WeightsIdentity,
    identify_weights,
    load_checked_weights,
    load_weights,
)
from rangeret.inference.model_set import ModelSet
from rangeret.inference.predictor import Predictor
from rangeret.inference.runtime.memory import release_freed_memory
from rangeret.inference.scan_worker import ScanWorker
from service.labelling.batching import ScanBatcher
from service.labelling.panoptic import model_clustering
from service.labelling.pooled import ModelRuntime
from service.models.pool import ModelPool

#: When the gateway checked its models, and what serves a model whose checkpoint changed since.
STARTED = "the gateway started"
REMEDY = "restart the gateway to serve it"


class ModelLoader:
    """Loads the models of a `ModelSet` for the pool, each behind a batcher of `batch_size`
    scans gathered for at most `max_wait` seconds."""

    def __init__(self, models: ModelSet, batch_size: int = 1, max_wait: float = 0.01) -> None:
        self.models = models
        self.batch_size = batch_size
        self.max_wait = max_wait
        #: Each model's weights as first checked, by name.
        self.identities: dict[str, WeightsIdentity] = {}

    def __call__(self, name: str) -> ModelRuntime:
        """The model `name` loaded: its checkpoint read, checked against what it was at start,
        its network built, moved to its device and warmed up. Its predictor finds no objects:
        a panoptic request or job asks for them, as the spec's clustering options say."""
        release_freed_memory()  # what the networks evicted for this load held
        spec = self.models.spec(name)
        checked = self.identities.get(name)
        weights = load_checked_weights(
            spec, checked.sha256 if checked else None, f"model {name}", f"when {STARTED}", REMEDY
        )
        checked = self.identities.setdefault(name, weights.identity)
        weights.identity.check_same(checked.describe(), name, STARTED, REMEDY)
        predictor = Predictor(weights, spec.replace(panoptic=False))
        batcher = ScanBatcher(ScanWorker(predictor), self.batch_size, self.max_wait)
        return ModelRuntime(batcher, predictor, model_clustering(spec))

    def identify(self, name: str) -> WeightsIdentity:
        """The identity of the model `name`, its network not built, except where an onnxruntime
        export must be made now (so that workers started next load it from the cache): then it
        is built for the export and dropped."""
        spec = self.models.spec(name)
        if spec.backend == "onnxruntime" and spec.onnx is None:
            weights = load_weights(spec)
            weights.export_onnx()
            identity = weights.identity
        else:
            identity = identify_weights(spec)
        self.identities[name] = identity
        return identity

    def check(self, name: str, pool: ModelPool[ModelRuntime] | None) -> WeightsIdentity:
        """Check the model `name` at start: loaded into `pool` where it has a free slot, else
        identified (`identify`); its identity either way."""
        if pool is None or not pool.free_slots():
            return self.identify(name)
        pool.acquire(name)  # loaded by this loader, which records what it found
        pool.release(name)
        return self.identities[name]
