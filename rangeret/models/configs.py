"""Named configurations of the two RangeRet networks and the thesis's ablation switches.

`rangeret-thesis` is the final model of the thesis (chapter 3; Table 5.8, last row): convolutional
REM 5-32-64-128, 7x7 patches with stride 4, 4 RetNet blocks of width 128 with 4 heads, retention with
the exponential Manhattan decay, and the REM-to-head residual. At 64x1024 with 20 classes it has
1,699,220 parameters. Table 5.8 prints 1.69 M and Table 4.15 1.7 M: the same count, cut and rounded
to two significant figures. The difference from 1.69 M exactly (+0.55 %) is all in rounding: the
parameters are the thesis's own (REM 94,272; patch embedding 803,200; four blocks of 198,016
each, being W_Q, W_K, W_V, W_G and W_O without biases, the GroupNorm's affine, an FFN with biases
and two LayerNorms; head 9,684). With `mixer="attention"` (the Transformer rows of Table 5.8: no
gate and no GroupNorm) it has 1,566,100 (1.56 M in the thesis), and adding `rem="linear"` gives
1,497,684 (1.49 M).

`rangeret-cir` is the released network of the follow-up (circular retention): a residual-context
stem, 8 blocks of softmax retention whose logits carry a circular Manhattan decay bias, a
depthwise-convolution FFN and a BatchNorm head. It has 3,761,876 parameters with 8 blocks.

The parameter counts do not depend on the resolution; the decay does, through the patch grid.

Override names: `layers`, `heads`, `dim`, `patch_size`, `stride`, `mixer`
("retention" | "attention"), `decay` ("unidirectional" | "bidirectional" | "manhattan" |
"exp-manhattan" | "circular"), `rem` ("conv" | "linear") and `residual`. `mixer="retention"` is
each network's own decay-weighted mixer; `"attention"` is plain softmax attention with no decay,
so it takes no `decay`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from rangeret.dataset.fields import is_int
from rangeret.exceptions import ModelError
from rangeret.models.blocks.decay import DECAYS
from rangeret.models.blocks.embedding import patch_grid

FAMILIES = ("thesis", "cir")
MIXERS = ("retention", "attention")
REMS = ("conv", "linear")
OVERRIDES = ("layers", "heads", "dim", "patch_size", "stride", "mixer", "decay", "rem", "residual")


class ModelConfigError(ModelError, ValueError):
    """A network that cannot be configured: an unknown model, override or size."""


@dataclass(frozen=True)
class ModelConfig:
    """Everything that defines one RangeRet network: its name, resolution, sizes and switches."""

    name: str
    family: str
    height: int
    width: int
    num_classes: int
    in_channels: int
    dim: int
    layers: int
    heads: int
    patch_size: tuple[int, int]
    stride: tuple[int, int]
    mixer: str
    decay: str | None
    rem: str
    residual: bool
    ffn_ratio: int
    value_factor: int
    head_dim: int

    def __post_init__(self) -> None:
        _check(self.family in FAMILIES, f"family must be one of {FAMILIES}, got {self.family!r}")
        for field in (
            "height",
            "width",
            "num_classes",
            "in_channels",
            "dim",
            "layers",
            "heads",
            "ffn_ratio",
            "value_factor",
            "head_dim",
        ):
            value = getattr(self, field)
            _check(
                is_int(value) and value >= 1, f"{field} must be a positive integer, got {value!r}"
            )
        for field in ("patch_size", "stride"):
            pair = getattr(self, field)
            _check(
                isinstance(pair, tuple)
                and len(pair) == 2
                and all(is_int(v) and v >= 1 for v in pair),
                f"{field} must be a pair of positive integers, got {pair!r}",
            )
        _check(self.mixer in MIXERS, f"mixer must be one of {MIXERS}, got {self.mixer!r}")
        if self.mixer == "attention":
            _check(
                self.decay is None,
                "mixer 'attention' is softmax attention without decay: leave decay unset",
            )
        else:
            _check(self.decay in DECAYS, f"decay must be one of {DECAYS}, got {self.decay!r}")
        _check(self.rem in REMS, f"rem must be one of {REMS}, got {self.rem!r}")
        _check(isinstance(self.residual, bool), f"residual must be a bool, got {self.residual!r}")
        _check(
            self.dim % (2 * self.heads) == 0,
            f"dim ({self.dim}) must be a multiple of 2 x heads ({self.heads}): keys are rotated in pairs",
        )
        _check(self.dim % 4 == 0, f"dim must be a multiple of 4, got {self.dim}")
        _check(
            self.height >= self.patch_size[0] and self.width >= self.patch_size[1],
            f"a {self.height}x{self.width} image holds no {self.patch_size[0]}x{self.patch_size[1]} patch",
        )

    @property
    def grid(self) -> tuple[int, int]:
        """Patch grid (Hp, Wp) at the configured resolution (thesis Eq. 3.6)."""
        return patch_grid(self.height, self.width, self.patch_size, self.stride)

    @property
    def key_dim(self) -> int:
        """Query and key width of one head."""
        return self.dim // self.heads

    @property
    def value_dim(self) -> int:
        """Value width of one head (the thesis doubles it)."""
        return self.value_factor * self.dim // self.heads

    def overrides(self) -> dict[str, Any]:
        """The override switches as this configuration sets them."""
        return {name: getattr(self, name) for name in OVERRIDES}

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (lists for pairs), stored in checkpoints."""
        return {
            k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ModelConfig:
        """Inverse of `to_dict`; unknown or missing fields raise ValueError."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        missing = sorted(names - set(data))
        _check(not unknown, f"unknown configuration fields: {', '.join(unknown)}")
        _check(not missing, f"configuration fields missing: {', '.join(missing)}")
        values = dict(data)
        for field in ("patch_size", "stride"):
            values[field] = _pair(values[field], field)
        return cls(**values)


_THESIS = {
    "family": "thesis",
    "in_channels": 5,
    "dim": 128,
    "layers": 4,
    "heads": 4,
    "patch_size": (7, 7),
    "stride": (4, 4),
    "mixer": "retention",
    "decay": "exp-manhattan",
    "rem": "conv",
    "residual": True,
    "ffn_ratio": 2,
    "value_factor": 2,
    "head_dim": 64,
}
_CIR = {**_THESIS, "family": "cir", "layers": 8, "decay": "circular"}

#: The named networks, as data: every field of `ModelConfig` except name and resolution.
CONFIGS: dict[str, dict[str, Any]] = {"rangeret-thesis": _THESIS, "rangeret-cir": _CIR}


def list_models() -> list[str]:
    """Names accepted by `build_model`."""
    return sorted(CONFIGS)


def resolve_config(
    name: str, height: int = 64, width: int = 1024, num_classes: int = 20, **overrides: Any
) -> ModelConfig:
    """The configuration of network `name` at a resolution, with ablation switches applied."""
    if name not in CONFIGS:
        raise ModelConfigError(f"unknown model {name!r}; known models: {', '.join(list_models())}")
    unknown = sorted(set(overrides) - set(OVERRIDES))
    if unknown:
        raise ModelConfigError(
            f"unknown overrides {', '.join(unknown)}; accepted: {', '.join(OVERRIDES)}"
        )
    values = {**CONFIGS[name], **overrides}
    for field in ("patch_size", "stride"):
        values[field] = _pair(values[field], field)
    if values["mixer"] == "attention":
        if overrides.get("decay") is not None:
            raise ModelConfigError(
                "mixer 'attention' is softmax attention without decay; drop the decay override"
            )
        values["decay"] = None
    return ModelConfig(name=name, height=height, width=width, num_classes=num_classes, **values)


def _pair(value: Any, field: str) -> tuple[int, int]:
    """An int or a pair of ints as a pair (patch sizes and strides may be given either way)."""
    if is_int(value):
        return (value, value)
    if isinstance(value, (list, tuple)) and len(value) == 2 and all(is_int(v) for v in value):
        return (value[0], value[1])
    raise ModelConfigError(f"{field} must be an int or a pair of ints, got {value!r}")


def _check(condition: bool, message: str) -> None:
    """ModelConfigError(message) unless `condition` holds."""
    if not condition:
        raise ModelConfigError(message)
