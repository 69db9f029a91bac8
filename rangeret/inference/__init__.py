"""From points to labels: the spec of a run (`spec.InferenceSpec`, torch-free) and its one weights
loader (`loaded_weights.load_weights`), the predictor and its one batch entry point
(`Predictor.label_projections`), the single-scan worker, kNN refinement, point labels, batch
loading, stage timing, what every runner reports (`results`), the runners of trees, files and
bags, and the forward-pass runtime (`runtime/`)."""

from __future__ import annotations

from rangeret import lazy_exports

#: The names importable from the package itself (`from rangeret.inference import InferenceSpec`),
#: each loaded from its module on first use: importing the package, or any module of it, costs
#: no more than before.
_EXPORTS = {
    "InferenceSpec": "rangeret.inference.spec",
    "InferenceSpecError": "rangeret.inference.spec",
}

__all__ = sorted(_EXPORTS)


__getattr__ = lazy_exports(__name__, _EXPORTS)
