"""`TrainConfig`: everything that defines a training run, as plain data, and its schema.

Each field carries its own command-line help in its metadata (`setting`): the `rangeret train`
options, the YAML configuration file (`rangeret.training.config_file`) and the checks of that
file are all derived from these fields, so a setting is written once. The nine settings a network
run shares (profile, model, height, width, fov_up, fov_down, batch_size, device, precision) are
declared once for both in `rangeret.inference.network_fields`, with their checks.

A config travels to Ray workers as a dict, is stored in every checkpoint's metadata and in the
resume state, and a resumed run must agree with it on every field that changes the arithmetic
(`RUNTIME_FIELDS` are the ones that may differ). The dataset profile is held by name (a built-in)
or by absolute file path; `dataset_profile()` resolves it with the explicit options in its place.
`precision` is one of `rangeret.inference.runtime.precision.PRECISIONS`; the trainer records the
one it resolves to (`auto` as `rangeret.inference.runtime.precision.auto_choice` picks), so a
resumed run keeps the arithmetic it started with.
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
from rangeret.inference.network_fields import (
    BATCH_SIZE,
    DEVICE,
    FOV_DOWN,
    FOV_UP,
    HEIGHT,
    MODEL,
    PROFILE,
    TRAINING_PRECISION,
    WIDTH,
)
from rangeret.models.configs import OVERRIDES
from rangeret.models.weights.hub import published_name
from rangeret.training.losses import LOSSES, WEIGHTINGS
from rangeret.training.range_mixes import MIXES
from rangeret.training.schedule import OPTIMIZERS, SCHEDULES

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
    """Training settings that cannot be used: unknown, out of range, contradictory, or a
    configuration file that does not hold them."""


def profile_reference(name_or_path: str | Path | None) -> str:
    """How a config holds a profile: a built-in's name as given, a file as its absolute path
    (workers in other folders and resumed runs read the same file); None is the default."""
    if name_or_path is None:
        return DEFAULT_PROFILE
    text = str(name_or_path)
    return text if text in BUILTIN_PROFILES else str(Path(text).resolve())


def absolute_path(path: str | Path) -> str:
    """`path` made absolute, so that workers in other folders and resumed runs read the same one."""
    return str(Path(path).resolve())


def parent_reference(value: str | Path) -> str:
    """How a config holds `--init-from`: a published model's name as given, a file as its
    absolute path (workers in other folders and resumed runs read the same one)."""
    text = str(value)
    return text if published_name(text) is not None else absolute_path(text)


def parse_override(text: str) -> tuple[str, Any]:
    """'name=value' as (name, value): ints, booleans and 'AxB' pairs are converted."""
    name, sep, value = text.partition("=")
    name = name.strip().replace("-", "_")
    if not sep or name not in OVERRIDES:
        raise TrainConfigError(
            f"--override takes NAME=VALUE with NAME one of {', '.join(OVERRIDES)}, got {text!r}"
        )
    value = value.strip()
    if value.lower() in ("true", "false"):
        return name, value.lower() == "true"
    if value.isdigit():
        return name, int(value)
    parts = value.lower().replace(",", "x").split("x")
    if len(parts) == 2 and all(p.isdigit() for p in parts):
        return name, (int(parts[0]), int(parts[1]))
    return name, value


def setting(default: Any = dataclasses.MISSING, *, help: str, group: str, **cli: Any) -> Any:
    """A `TrainConfig` field with its schema: `help` and `group` of its command-line option, and
    optionally `flag`, `metavar`, `nargs`, `choices`, `negate` (a bool option that turns the field
    off), `required` (to be given on the command line or in the file, even with a default),
    `settled_by` (the name of a setting that, when given, settles a required one left out),
    `resolve` (a function applied to every given value, e.g. `absolute_path`), `parse` (applied
    to each item given on the command line, which then add to the file's mapping), `keys` (the
    names of a mapping setting), `default_text` (how the help shows the default) and `flag=None`
    (no option). The settings shared with `InferenceSpec` are made by their `FieldSchema.field`
    instead, which fills in the same keys."""
    return dataclasses.field(default=default, metadata={"help": help, "group": group, **cli})


@dataclass(frozen=True, kw_only=True)
class TrainConfig:
    """A training run: data, network, optimisation, augmentation and bookkeeping.

    `profile` names the dataset profile (layout, point record, projection, labels, kNN rule);
    `height`, `width`, `fov_up`, `fov_down` and `label_config` of None take the profile's values.
    `init_from` names a checkpoint to start from (`rangeret.training.init_from`): `model` and
    `model_overrides` must then be its network's, and `freeze_backbone_steps` keeps what it
    loaded unchanged for that many steps.
    `train_sequences` / `val_sequences` of None mean the profile's "train" / "valid" splits; an
    empty `val_sequences` means no validation (best.pt then follows the training loss).
    `max_steps` caps the run, and the schedule then spans min(epochs x steps per epoch, max_steps)
    steps. `model_overrides` are the ablation switches of `build_model`.
    """

    dataset: str = setting(
        help="dataset tree in the profile's layout (SemanticKITTI: ROOT/sequences/XX/{velodyne,labels})",
        group="data",
        metavar="ROOT",
        required=True,
        resolve=absolute_path,
    )
    profile: str = dataclasses.replace(PROFILE, default=DEFAULT_PROFILE, default_text=None).field(
        group="data", resolve=profile_reference
    )
    train_sequences: tuple[str, ...] | None = setting(
        None,
        help="training sequences",
        group="data",
        metavar="XX",
        default_text="the profile's train split",
    )
    val_sequences: tuple[str, ...] | None = setting(
        None,
        help="validation sequences; give none to skip validation",
        group="data",
        metavar="XX",
        nargs="*",
        default_text="the valid split",
    )
    label_config: str | None = setting(
        None,
        help="label configuration (.json of this project or an official .yaml) in place of the "
        "profile's",
        group="data",
        metavar="FILE",
        resolve=absolute_path,
    )
    height: int | None = HEIGHT.field(group="data")
    width: int | None = WIDTH.field(group="data")
    fov_up: float | None = FOV_UP.field(group="data")
    fov_down: float | None = FOV_DOWN.field(group="data")
    augment: bool = setting(
        True,
        help="no point augmentation (scale, rotation, shift, flip)",
        group="data",
        flag="--no-augment",
        negate=True,
    )
    mixes: tuple[str, ...] = setting(
        (),
        help=f"RangeFormer's range-image mixes to apply ({', '.join(MIXES)})",
        group="data",
        metavar="MIX",
        choices=MIXES,
    )
    mix_probability: float = setting(
        0.5, help="probability of each chosen mix per sample", group="data", metavar="P"
    )
    loader_workers: int = setting(
        2,
        help="data-loading processes per trainer; 0 loads in the training process",
        group="data",
        metavar="N",
    )
    model: str = dataclasses.replace(MODEL, default="rangeret-thesis", default_text=None).field(
        note="with --init-from the checkpoint's, which it may only repeat",
        group="network",
        required=True,
        settled_by="init_from",
    )
    model_overrides: tuple[tuple[str, Any], ...] = setting(
        (),
        help=f"ablation switch of the network ({', '.join(OVERRIDES)}), e.g. decay=manhattan; "
        "repeatable",
        group="network",
        flag="--override",
        metavar="NAME=VALUE",
        parse=parse_override,
        keys=OVERRIDES,
    )
    init_from: str | None = setting(
        None,
        help="start from the weights of a checkpoint file or a published model (a name of "
        "`rangeret weights list`) at step 0 with a new optimiser: its network, every tensor that "
        "fits, a new head where the profile's classes differ",
        group="network",
        metavar="CHECKPOINT",
        resolve=parent_reference,
    )
    freeze_backbone_steps: int = setting(
        0,
        help="with --init-from, train only the new head for the first N steps: the loaded "
        "tensors and their BatchNorm statistics stay as loaded",
        group="network",
        metavar="N",
    )
    epochs: int = setting(64, help="training epochs", group="optimisation", metavar="N")
    max_steps: int | None = setting(
        None,
        help="stop after N steps; the schedule then spans min(epochs x steps per epoch, N)",
        group="optimisation",
        metavar="N",
    )
    batch_size: int = BATCH_SIZE.field(note="per trainer, 1 in the thesis", group="optimisation")
    optimizer: str = setting(
        "adamw", help="the optimiser", group="optimisation", choices=tuple(OPTIMIZERS)
    )
    lr: float = setting(
        1e-3, help="learning rate, where the schedule starts", group="optimisation", metavar="LR"
    )
    max_lr: float = setting(
        1e-2, help="peak of the schedule", group="optimisation", metavar="MAX_LR"
    )
    weight_decay: float = setting(
        0.05, help="weight decay", group="optimisation", metavar="WEIGHT_DECAY"
    )
    schedule: str = setting(
        "onecycle",
        help="onecycle (the thesis's) or linear warm-up + cosine",
        group="optimisation",
        choices=SCHEDULES,
    )
    warmup: float = setting(
        0.3,
        help="share of the steps spent warming up; chapter 5 used 0.02",
        group="optimisation",
        metavar="SHARE",
    )
    losses: tuple[str, ...] = setting(
        LOSSES,
        help="losses to sum with equal weights",
        group="optimisation",
        flag="--loss",
        choices=LOSSES,
        default_text="all three",
    )
    class_weighting: str = setting(
        "inverse-sqrt",
        help="cross-entropy class weights from class frequencies; inverse-sqrt is 1/sqrt(f + 1e-3)",
        group="optimisation",
        flag="--class-weights",
        choices=WEIGHTINGS,
    )
    focal_gamma: float = setting(
        2.0, help="focusing exponent of the focal loss", group="optimisation", metavar="FOCAL_GAMMA"
    )
    clip_grad: float = setting(
        1.0,
        help="clip the gradient norm; 0 turns clipping off",
        group="optimisation",
        metavar="NORM",
    )
    precision: str = TRAINING_PRECISION.field(group="optimisation")
    seed: int = setting(
        0,
        help="seed of initialisation, order and augmentation",
        group="optimisation",
        metavar="SEED",
    )
    out: str = setting(
        help="writes last.pt, best.pt, last.state.pt, metrics.csv, steps.csv, curves.png",
        group="run",
        metavar="DIR",
        required=True,
        resolve=absolute_path,
    )
    resume: bool = setting(False, help="continue the run saved in DIR exactly", group="run")
    checkpoint_every: int = setting(
        0,
        help="also save last.pt and the state every N steps",
        group="run",
        metavar="N",
        default_text="at epoch ends",
    )
    device: str = DEVICE.field(group="run")
    progress: bool = setting(True, help="progress bars (-q turns them off)", group="run", flag=None)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            schema = f.metadata.get("schema")
            problem = schema.problem(getattr(self, f.name)) if schema else None
            if problem is not None:
                raise TrainConfigError(problem)
        checks = [
            (self.epochs >= 1, f"epochs must be at least 1, got {self.epochs}"),
            (
                self.max_steps is None or self.max_steps >= 1,
                f"max_steps must be at least 1, got {self.max_steps}",
            ),
            (
                self.optimizer in OPTIMIZERS,
                f"optimizer must be one of {tuple(OPTIMIZERS)}, got {self.optimizer!r}",
            ),
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
            (
                self.freeze_backbone_steps >= 0,
                f"freeze_backbone_steps must not be negative, got {self.freeze_backbone_steps}",
            ),
            (
                self.freeze_backbone_steps == 0 or self.init_from is not None,
                f"--freeze-backbone-steps {self.freeze_backbone_steps} needs --init-from: only "
                "weights loaded from a checkpoint can stay frozen while a new head trains",
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
        """Inverse of `to_dict`; unknown fields raise TrainConfigError. The `amp` flag of runs saved
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
            values["model_overrides"] = override_pairs(values["model_overrides"])
        return cls(**values)

    def differences(self, other: TrainConfig) -> list[str]:
        """'field: stored -> now' for every field outside `RUNTIME_FIELDS` that differs."""
        mine, theirs = self.to_dict(), other.to_dict()
        return [
            f"{name}: {mine[name]!r} -> {theirs[name]!r}"
            for name in mine
            if name not in RUNTIME_FIELDS and mine[name] != theirs[name]
        ]


def override_pairs(overrides: Mapping[str, Any] | Any) -> tuple[tuple[str, Any], ...]:
    """Model overrides as `TrainConfig` holds them, from a mapping or (name, value) pairs, with
    lists (a patch size read from a file) as tuples."""
    items = overrides.items() if isinstance(overrides, Mapping) else overrides
    return tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in items)
