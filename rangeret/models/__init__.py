"""RangeRet networks: the thesis model with its ablations and the released circular-retention model.

`build_model(name, height, width, num_classes, **overrides)` builds one by name (`list_models()`);
`load_checkpoint(path, ...)` loads a published state_dict or the project's own self-describing
checkpoint, which `save_checkpoint` writes. Modules map to the thesis: `stem` (REM), `embedding`
(VEM), `decay`, `position`, `token_mixing`, `kernels` and `retention` (multi-scale retention),
`ffn`, `backbone` (RetNet blocks), `head` (Semantic Head), `rangeret` (the whole network and
`build_model`), `configs`, `checkpoint` (reading and writing files) and `checkpoint_info` (what a
file held).
"""

from rangeret.models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from rangeret.models.checkpoint_info import CheckpointInfo
from rangeret.models.configs import ModelConfig, list_models
from rangeret.models.rangeret import RangeRet, build_model

__all__ = [
    "CheckpointError",
    "CheckpointInfo",
    "ModelConfig",
    "RangeRet",
    "build_model",
    "list_models",
    "load_checkpoint",
    "save_checkpoint",
]
