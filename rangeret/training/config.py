"""`TrainConfig`: everything that defines a training run, as plain data.

It travels to Ray workers as a dict, is stored in every checkpoint's metadata and in the resume
state, and a resumed run must agree with it on every field that changes the arithmetic
(`RUNTIME_FIELDS` are the ones that may differ). The dataset profile is held by name (a built-in)
or by absolute file path; `dataset_profile()` resolves it with the explicit options in its place.
`precision` is one of `rangeret.inference.runtime.precision.PRECISIONS`; the trainer records the one it resolves to
(`auto` is fp16 on CUDA, fp32 on the CPU), so a resumed run keeps the arithmetic it started with.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rangeret.dataset.labels import LabelConfig, load_label_config
from rangeret.dataset.profiles import (
    BUILTIN_PROFILES,
    DEFAULT_PROFILE,
    DatasetProfile,
    load_profile,
)
from rangeret.dataset.projection import ProjectionConfig
from rangeret.exceptions import ConfigError
from rangeret.inference.runtime.precision import PRECISIONS
from rangeret.training.losses import LOSSES, WEIGHTINGS
from rangeret.training.range_mixes import MIXES
from rangeret.training.schedule import SCHEDULES

#: Fields a resumed run may change: where and how it runs, not what it computes.
RUNTIME_FIELDS = (
    "dataset",
    "out",
    "resume",
    "progress",
    "loader_workers",
    "device",
    "checkpoint_every",
)


class TrainConfigError(ConfigError, ValueError):
    """Training settings that cannot be used: out of range, contradictory or unknown."""


@dataclass(frozen=True)
class TrainConfig:
    """A training run: data, network, optimisation, augmentation and bookkeeping.

    `profile` names the dataset profile (layout, point record, projection, labels, kNN rule);
    `height`, `width`, `fov_up`, `fov_down` and `label_config` of None take the profile's values.
    `train_sequences` / `val_sequences` of None mean the profile's "train" / "valid" splits; an empty `val_sequences` means no validation (best.pt then follows the training loss).
    `max_steps` caps the run, and the schedule then spans min(epochs x steps per epoch, max_steps)
    steps. `model_overrides` are the ablation switches of `build_model`.
    """

    dataset: str
    out: str
    model: str = "rangeret-thesis"
    profile: str = DEFAULT_PROFILE
    height: int | None = None
    width: int | None = None
    fov_up: float | None = None
    fov_down: float | None = None
    label_config: str | None = None
    train_sequences: tuple[str, ...] | None = None
    val_sequences: tuple[str, ...] | None = None
    model_overrides: tuple[tuple[str, Any], ...] = ()
    epochs: int = 64
    max_steps: int | None = None
    batch_size: int = 1
    lr: float = 1e-3
    max_lr: float = 1e-2
    weight_decay: float = 0.05
    schedule: str = "onecycle"
    warmup: float = 0.3
    losses: tuple[str, ...] = LOSSES
    class_weighting: str = "inverse-sqrt"
    focal_gamma: float = 2.0
    clip_grad: float = 1.0
    precision: str = "auto"
    augment: bool = True
    mixes: tuple[str, ...] = ()
    mix_probability: float = 0.5
    seed: int = 0
    device: str = "auto"
    loader_workers: int = 2
    checkpoint_every: int = 0
    resume: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        checks = [
            (self.epochs >= 1, f"epochs must be at least 1, got {self.epochs}"),
            (
                self.max_steps is None or self.max_steps >= 1,
                f"max_steps must be at least 1, got {self.max_steps}",
            ),
            (self.batch_size >= 1, f"batch_size must be at least 1, got {self.batch_size}"),
            (
                self.lr > 0 and self.max_lr >= self.lr,
                f"need 0 < lr <= max_lr, got {self.lr} and {self.max_lr}",
            ),
            (self.weight_decay >= 0, f"weight_decay must not be negative, got {self.weight_decay}"),
            (
                self.schedule in SCHEDULES,
                f"schedule must be one of {SCHEDULES}, got {self.schedule!r}",
            ),
            (0 < self.warmup < 1, f"warmup must lie in (0, 1), got {self.warmup}"),
            (
                bool(self.losses) and set(self.losses) <= set(LOSSES),
                f"losses must be chosen from {LOSSES}, got {self.losses}",
            ),
            (
                self.class_weighting in WEIGHTINGS,
                f"class_weighting must be one of {WEIGHTINGS}, got {self.class_weighting!r}",
            ),
            (self.focal_gamma >= 0, f"focal_gamma must not be negative, got {self.focal_gamma}"),
            (
                self.clip_grad >= 0,
                f"clip_grad must not be negative (0 turns clipping off), got {self.clip_grad}",
            ),
            (
                self.precision in PRECISIONS,
                f"precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}",
            ),
            (set(self.mixes) <= set(MIXES), f"mixes must be chosen from {MIXES}, got {self.mixes}"),
            (
                0 <= self.mix_probability <= 1,
                f"mix_probability must lie in [0, 1], got {self.mix_probability}",
            ),
            (self.seed >= 0, f"seed must not be negative, got {self.seed}"),
            (
                self.loader_workers >= 0,
                f"loader_workers must not be negative, got {self.loader_workers}",
            ),
            (
                self.checkpoint_every >= 0,
                f"checkpoint_every must not be negative, got {self.checkpoint_every}",
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise TrainConfigError(message)

    def dataset_profile(self, labels: LabelConfig | None = None) -> DatasetProfile:
        """The profile this run trains with: `profile` with the explicit projection options and
        label configuration (`labels`, else the `label_config` file) in place of its own."""
        if labels is None and self.label_config is not None:
            labels = load_label_config(self.label_config)
        return load_profile(self.profile).with_overrides(
            height=self.height,
            width=self.width,
            fov_up=self.fov_up,
            fov_down=self.fov_down,
            labels=labels,
        )

    def with_projection(self, projection: ProjectionConfig) -> TrainConfig:
        """The config with `projection`'s values for the projection options left to the profile,
        so that runs are compared on the values they actually use."""
        values = {
            name: getattr(projection, name)
            for name in ("height", "width", "fov_up", "fov_down")
            if getattr(self, name) is None
        }
        return dataclasses.replace(self, **values)

    @property
    def overrides(self) -> dict[str, Any]:
        """The model overrides as keyword arguments."""
        return dict(self.model_overrides)

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (lists for tuples), for checkpoints, the resume state and Ray workers."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "model_overrides":
                value = {k: list(v) if isinstance(v, tuple) else v for k, v in value}
            elif isinstance(value, tuple):
                value = list(value)
            out[f.name] = value
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainConfig:
        """Inverse of `to_dict`; unknown fields raise ValueError. The `amp` flag of runs saved
        before `precision` existed reads as precision auto (amp on) or fp32 (amp off)."""
        values = dict(data)
        if "amp" in values and "precision" not in values:
            values["precision"] = "auto" if values.pop("amp") else "fp32"
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise TrainConfigError(f"unknown training settings: {', '.join(unknown)}")
        for key in ("train_sequences", "val_sequences", "losses", "mixes"):
            if values.get(key) is not None:
                values[key] = tuple(values[key])
        if "model_overrides" in values:
            overrides = values["model_overrides"]
            items = overrides.items() if isinstance(overrides, Mapping) else overrides
            values["model_overrides"] = tuple(
                (k, tuple(v) if isinstance(v, list) else v) for k, v in items
            )
        return cls(**values)

    def differences(self, other: TrainConfig) -> list[str]:
        """'field: stored -> now' for every field outside `RUNTIME_FIELDS` that differs."""
        mine, theirs = self.to_dict(), other.to_dict()
        return [
            f"{name}: {mine[name]!r} -> {theirs[name]!r}"
            for name in mine
            if name not in RUNTIME_FIELDS and mine[name] != theirs[name]
        ]


def profile_reference(name_or_path: str | Path | None) -> str:
    """How a config holds a profile: a built-in's name as given, a file as its absolute path
    (workers in other folders and resumed runs read the same file); None is the default."""
    if name_or_path is None:
        return DEFAULT_PROFILE
    text = str(name_or_path)
    return text if text in BUILTIN_PROFILES else str(Path(text).resolve())
