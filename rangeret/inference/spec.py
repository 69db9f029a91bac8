"""`InferenceSpec`: which network runs, on which data, and how, as one frozen record.

Every runner takes its network from a spec: `rangeret predict` and the other commands build it
from their options, the Serve application from its arguments, a gateway's Ray job from one JSON
option, the library from keywords. Each field is declared by a `FieldSchema`
(`rangeret.inference.network_fields`, which also holds the fields `TrainConfig` shares) with its
command-line help, kind, default and allowed values, so the command line's network options
(`add_spec_options`), the checks of a mapping (`InferenceSpec.from_mapping`) and the mapping sent
to another process (`to_mapping`) are all derived from the fields: a network option is written
once. Torch-free, since every `rangeret` call builds its parser from it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rangeret.dataset.fields import is_int, is_number
from rangeret.exceptions import InputError
from rangeret.inference.network_fields import (
    BATCH_SIZE,
    DEVICE,
    FOV_DOWN,
    FOV_UP,
    HEIGHT,
    KIND_NAMES,
    MODEL,
    PRECISION,
    PROFILE,
    WIDTH,
    FieldSchema,
    option_help,
)
from rangeret.inference.runtime.backends import BACKENDS, RuntimeChoiceError, check_backend
from rangeret.inference.settings import (
    DEFAULT_CLUSTER_ANGLE,
    DEFAULT_KNN,
    DEFAULT_MIN_CLUSTER_POINTS,
    ClusterSettings,
    KnnSettings,
    TtaSettings,
)

#: The field groups: which weights load (every command that loads a network, `export`
#: included), and how a run uses them.
WEIGHTS, RUN = "weights", "run"


class InferenceSpecError(InputError, ValueError):
    """A network option that is unknown or has a value it cannot take: one sentence naming it."""


def option(
    schema: FieldSchema,
    *,
    group: str,
    note: str = "",
    negate: str | None = None,
    cli_type: Callable[[str], Any] | None = None,
) -> Any:
    """An `InferenceSpec` field of `schema` (`note` added to its help) in `group` (`WEIGHTS` or
    `RUN`), with `negate` (a bool option spelt as the flag that turns it off) and `cli_type`
    (how the command line reads it, where not by its kind)."""
    return schema.field(note=note, group=group, negate=negate, cli_type=cli_type)


@dataclass(frozen=True, kw_only=True)
class InferenceSpec:
    """Everything that decides a run's network and its labels, as plain values.

    `checkpoint` is a file or a published model's name (None: the bundled demo weights);
    `profile` a built-in profile's name or a YAML file (None: the checkpoint's, else
    semantickitti); `model`, `height`, `width`, `fov_up` and `fov_down` of None take what the
    checkpoint or the profile says. `knn` False takes each point's pixel class.
    """

    checkpoint: str | None = option(
        FieldSchema(
            "checkpoint",
            str,
            "weights: a published model's name (`rangeret weights list`: rangeret-kitti-657, "
            "rangeret-panda-600, rangeret-poss-528; fetched from the cache or the model hub, with "
            "its profile), the project's own checkpoint or a published .pt file",
            default_text="the bundled demo weights, trained on simulated scenes only",
            metavar="FILE",
        ),
        group=WEIGHTS,
        cli_type=Path,
    )
    profile: str | None = option(PROFILE, group=WEIGHTS)
    model: str | None = option(MODEL, group=WEIGHTS)
    height: int | None = option(HEIGHT, group=WEIGHTS)
    width: int | None = option(WIDTH, group=WEIGHTS)
    fov_up: float | None = option(FOV_UP, group=WEIGHTS)
    fov_down: float | None = option(FOV_DOWN, group=WEIGHTS)
    batch_size: int = option(BATCH_SIZE, group=RUN)
    knn: bool = option(
        FieldSchema(
            "knn", bool, "take each point's pixel class, without kNN refinement", default=True
        ),
        group=RUN,
        negate="--no-knn",
    )
    device: str = option(DEVICE, group=RUN)
    precision: str = option(PRECISION, group=RUN, note="always fp32 with --backend onnxruntime")
    backend: str = option(
        FieldSchema(
            "backend",
            str,
            "run the network in torch or in onnxruntime on its ONNX export, made once per "
            "checkpoint into $RANGERET_CACHE/onnx (else ~/.cache/rangeret/onnx); onnxruntime "
            "runs fp32 only, and on CUDA needs the onnxruntime-gpu package",
            default="torch",
            choices=BACKENDS,
        ),
        group=RUN,
    )
    onnx: str | None = option(
        FieldSchema(
            "onnx",
            str,
            "with --backend onnxruntime: run this export (`rangeret export`) rather than the "
            "cached one, once it agrees with the checkpoint, resolution, profile and batch size",
            metavar="FILE.onnx",
        ),
        group=RUN,
    )
    tta_flip: bool = option(
        FieldSchema(
            "tta_flip", bool, "test-time augmentation: add the mirrored view", default=False
        ),
        group=RUN,
    )
    tta_shifts: int = option(
        FieldSchema(
            "tta_shifts",
            int,
            "test-time augmentation: add N azimuth-rotated views",
            default=0,
            metavar="N",
            minimum=0,
        ),
        group=RUN,
    )

    panoptic: bool = option(
        FieldSchema(
            "panoptic",
            bool,
            "panoptic segmentation: also find the objects, each thing class's points clustered "
            "into instances on the range image, written as the benchmark's panoptic labels",
            default=False,
        ),
        group=RUN,
    )
    cluster_angle: float = option(
        FieldSchema(
            "cluster_angle",
            float,
            "with --panoptic: neighbouring points of one class join one object where the angle "
            "between the beam and the line through both exceeds this many degrees (lower joins "
            "more)",
            default=DEFAULT_CLUSTER_ANGLE,
            metavar="DEG",
        ),
        group=RUN,
    )
    min_cluster_points: int = option(
        FieldSchema(
            "min_cluster_points",
            int,
            "with --panoptic: a cluster of fewer points joins the nearest object of its class",
            default=DEFAULT_MIN_CLUSTER_POINTS,
            metavar="N",
            minimum=1,
        ),
        group=RUN,
    )

    def __post_init__(self) -> None:
        self._settle(_key)

    def _settle(self, name: Callable[[str], str]) -> None:
        """A checkpoint path held as its text, then `InferenceSpecError` for the first problem,
        each field spelt by `name`."""
        if isinstance(self.checkpoint, Path):
            object.__setattr__(self, "checkpoint", str(self.checkpoint))
        problem = self.problem(name)
        if problem is not None:
            raise InferenceSpecError(problem)

    # Reading and writing ------------------------------------------------------------------

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any], *, where: str = "") -> InferenceSpec:
        """A spec from network options by field name (a Serve application's arguments, a
        job's JSON); an unknown name or a bad value is one `InferenceSpecError` naming the key as
        the mapping spells it, with `where` (e.g. " of the Serve application") after it."""
        known = field_names()
        unknown = [str(k) for k in values if k not in known]
        if unknown:
            raise InferenceSpecError(
                f"unknown network option {', '.join(sorted(unknown))}{where}; the known ones are "
                f"{', '.join(known)}"
            )
        checked = {}
        for f in dataclasses.fields(cls):
            if f.name in values:
                checked[f.name] = _checked(f, values[f.name], f.name + where)
        return _made(cls, checked, lambda name: name + where)

    def to_mapping(self) -> dict[str, Any]:
        """The spec as JSON-safe network options by field name, those at their default left out:
        `from_mapping(to_mapping(s)) == s`."""
        return {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if getattr(self, f.name) != f.default
        }

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> InferenceSpec:
        """A spec from the options `add_spec_options` added (those a parser lacks keep their
        defaults); a bad value is one `InferenceSpecError` naming its option."""
        values = {
            f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)
        }
        return _made(cls, values, flag)

    def replace(self, **changes: Any) -> InferenceSpec:
        """The same spec with some fields changed (checked again)."""
        return dataclasses.replace(self, **changes)

    # What it means ------------------------------------------------------------------------

    def problem(self, name: Callable[[str], str]) -> str | None:
        """What is wrong with the fields taken together, each spelt by `name`; None when they can
        be used."""
        for f in dataclasses.fields(self):
            problem = f.metadata["schema"].problem(getattr(self, f.name), name(f.name))
            if problem is not None:
                return problem
        if self.onnx is not None and self.backend != "onnxruntime":
            return (
                f"{name('onnx')} is an export for {name('backend')} onnxruntime: add that, or "
                f"leave {name('onnx')} out"
            )
        if not 0 < self.cluster_angle < 90:
            return (
                f"{name('cluster_angle')} must be above 0 and below 90 degrees, got "
                f"{self.cluster_angle:g}"
            )
        try:
            check_backend(self.backend, self.precision)
        except RuntimeChoiceError as exc:
            return (
                str(exc)
                .replace("--backend", name("backend"))
                .replace("--precision", name("precision"))
            )
        return None

    @property
    def knn_settings(self) -> KnnSettings | None:
        """The kNN refinement the run applies (None: pixel classes)."""
        return DEFAULT_KNN if self.knn else None

    @property
    def clustering(self) -> ClusterSettings | None:
        """How objects are found (None: no panoptic segmentation)."""
        if not self.panoptic:
            return None
        return ClusterSettings(self.cluster_angle, self.min_cluster_points)

    @property
    def tta(self) -> TtaSettings | None:
        """The test-time augmentation of the run (None: the plain view only)."""
        if not (self.tta_flip or self.tta_shifts):
            return None
        return TtaSettings(flip=self.tta_flip, shifts=self.tta_shifts)


def _key(name: str) -> str:
    return name


def flag(name: str) -> str:
    """The command-line option of a field (`batch_size` is `--batch-size`, `knn` `--no-knn`)."""
    negate = _field(name).metadata["negate"]
    return negate or "--" + name.replace("_", "-")


def field_names() -> tuple[str, ...]:
    """The names of the spec's fields, in order."""
    return tuple(f.name for f in dataclasses.fields(InferenceSpec))


def _field(name: str) -> dataclasses.Field:
    return next(f for f in dataclasses.fields(InferenceSpec) if f.name == name)


def _fields(group: str) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(InferenceSpec) if f.metadata["group"] == group]


def _made(
    cls: type[InferenceSpec], values: Mapping[str, Any], name: Callable[[str], str]
) -> InferenceSpec:
    """The spec of checked values, settled as the constructor settles it but with its problems
    spelt with `name` (the constructor spells them by field name)."""
    spec = object.__new__(cls)
    for f in dataclasses.fields(cls):
        object.__setattr__(spec, f.name, values.get(f.name, f.default))
    spec._settle(name)
    return spec


def _checked(f: dataclasses.Field, value: Any, key: str) -> Any:
    """`value` for field `f`, or an `InferenceSpecError` naming `key`."""
    kind = f.metadata["schema"].kind
    if value is None and f.default is None:
        return None
    converted = _as_kind(kind, value)
    if converted is None:
        raise InferenceSpecError(f"{key} takes {KIND_NAMES[kind]}, got {value!r}")
    return converted


def _as_kind(kind: type, value: Any) -> Any:
    """`value` as `kind` (an integer or a finite number may come as its text), or None when it
    is not one."""
    if kind is bool or kind is str:
        return value if isinstance(value, kind) else None
    if isinstance(value, str):
        try:
            value = int(value) if kind is int else float(value)
        except ValueError:
            return None
    if kind is int:
        return int(value) if is_int(value) else None
    return float(value) if is_number(value) and math.isfinite(value) else None


def group_fields(group: str) -> tuple[str, ...]:
    """The names of the fields of one group (`WEIGHTS` or `RUN`), in order."""
    return tuple(f.name for f in _fields(group))


def add_spec_options(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    names: tuple[str, ...] | None = None,
) -> None:
    """The command line's options of the spec's fields `names` (default: all), in the fields'
    order, as `from_args` reads them back."""
    for f in dataclasses.fields(InferenceSpec):
        if names is not None and f.name not in names:
            continue
        schema, meta = f.metadata["schema"], f.metadata
        if schema.kind is bool:
            action = "store_false" if meta["negate"] else "store_true"
            parser.add_argument(flag(f.name), dest=f.name, action=action, help=option_help(f))
            continue
        kwargs: dict[str, Any] = {"help": option_help(f), "default": f.default}
        if schema.choices is not None:
            kwargs["choices"] = list(schema.choices)
        else:
            kwargs["type"] = meta["cli_type"] or schema.kind
        if schema.metavar is not None:
            kwargs["metavar"] = schema.metavar
        parser.add_argument(flag(f.name), dest=f.name, **kwargs)
