"""RangeRet networks: the thesis model with its ablations and the released circular-retention model.

`build_model(name, height, width, num_classes, **overrides)` builds one by name (`list_models()`);
`load_checkpoint(path, ...)` loads a published state_dict or the project's own self-describing
checkpoint, which `save_checkpoint` writes. `blocks/` holds the network's blocks, `network` the
whole network, `configs` its named configurations, and `weights/` everything about weight files.

The names below load on first use, so that torch-free parts of `weights/` (the registry, the
demo weights' description) import without torch.
"""

from __future__ import annotations

from rangeret import lazy_exports

_EXPORTS = {
    "CheckpointError": "rangeret.models.weights.checkpoint",
    "load_checkpoint": "rangeret.models.weights.checkpoint",
    "save_checkpoint": "rangeret.models.weights.checkpoint",
    "CheckpointInfo": "rangeret.models.weights.checkpoint_info",
    "ModelConfig": "rangeret.models.configs",
    "list_models": "rangeret.models.configs",
    "RangeRet": "rangeret.models.network",
    "build_model": "rangeret.models.network",
}

__all__ = sorted(_EXPORTS)


__getattr__ = lazy_exports(__name__, _EXPORTS)
