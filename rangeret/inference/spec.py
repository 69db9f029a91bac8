"""`InferenceSpec`: which network runs, on which data, and how, as one frozen record.

Every runner takes its network from a spec: `rangeret predict` and the other commands build it
from their options, the Serve application from its arguments, a gateway's Ray job from one JSON
option, the library from keywords. Each field carries its command-line help, type, default and
choices (`option`), so the command line's network options (`add_spec_options`), the checks of a
mapping (`InferenceSpec.from_mapping`) and the mapping sent to another process (`to_mapping`)
are all derived from the fields: a network option is written once. Torch-free, since every
`rangeret` call builds its parser from it.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rangeret.dataset.profiles import BUILTIN_PROFILES
from rangeret.dataset.projection import MAX_HEIGHT, MAX_WIDTH
from rangeret.exceptions import InputError
from rangeret.inference.runtime.backends import BACKENDS, RuntimeChoiceError, check_backend
from rangeret.inference.runtime.precision import PRECISIONS
from rangeret.inference.settings import DEFAULT_KNN, KnnSettings, TtaSettings

#: The networks a checkpoint can hold.
MODELS = ("rangeret-thesis", "rangeret-cir")
#: Where the network runs.
DEVICES = ("auto", "cpu", "cuda")
#: The field groups: which weights load (every command that loads a network, `export`
#: included), and how a run uses them.
WEIGHTS, RUN = "weights", "run"
_FOV = "vertical field of view (default: the profile's)"


class InferenceSpecError(InputError, ValueError):
    """A network option that is unknown or has a value it cannot take: one sentence naming it."""


def option(
    default: Any,
    *,
    help: str,
    group: str,
    kind: type = str,
    metavar: str | None = None,
    choices: tuple[str, ...] | None = None,
    negate: str | None = None,
    minimum: int | None = None,
    maximum: int | None = None,
    cli_type: Callable[[str], Any] | None = None,
) -> Any:
    """An `InferenceSpec` field with its schema: the value's `kind` (bool, int, float or, by
    default, str; None is allowed where the default is None), `help`, `metavar` and `choices` of
    its option, `group` (`WEIGHTS` or `RUN`), `negate` (a bool option spelt as the flag that
    turns it off), `minimum` and `maximum` (the least and the most integer it takes) and
    `cli_type` (how the command line reads it)."""
    metadata = {
        "help": help,
        "kind": kind,
        "group": group,
        "metavar": metavar,
        "choices": choices,
        "negate": negate,
        "minimum": minimum,
        "maximum": maximum,
        "cli_type": cli_type,
    }
    return dataclasses.field(default=default, metadata=metadata)


@dataclass(frozen=True, kw_only=True)
class InferenceSpec:
    """Everything that decides a run's network and its labels, as plain values.

    `checkpoint` is a file or a published model's name (None: the bundled demo weights);
    `profile` a built-in profile's name or a YAML file (None: the checkpoint's, else
    semantickitti); `model`, `height`, `width`, `fov_up` and `fov_down` of None take what the
    checkpoint or the profile says. `knn` False takes each point's pixel class.
    """

    checkpoint: str | None = option(
        None,
        group=WEIGHTS,
        metavar="FILE",
        cli_type=Path,
        help="weights: a published model's name (`rangeret weights list`: rangeret-kitti-657, "
        "rangeret-panda-600, rangeret-poss-528; fetched from the cache or the model hub, with "
        "its profile), the project's own checkpoint or a published .pt file (default: the "
        "bundled demo weights, trained on simulated scenes only)",
    )
    profile: str | None = option(
        None,
        group=WEIGHTS,
        metavar="NAME|FILE",
        help=f"dataset profile: {', '.join(BUILTIN_PROFILES)} or a YAML file "
        "(`rangeret profile show NAME` prints one to start from); default: the checkpoint's, "
        "else semantickitti",
    )
    model: str | None = option(
        None,
        group=WEIGHTS,
        choices=MODELS,
        help="network name; recognised from the checkpoint when omitted",
    )
    height: int | None = option(
        None,
        kind=int,
        group=WEIGHTS,
        minimum=1,
        maximum=MAX_HEIGHT,
        help=f"range image rows, at most {MAX_HEIGHT} (default: the profile's)",
    )
    width: int | None = option(
        None,
        kind=int,
        group=WEIGHTS,
        minimum=1,
        maximum=MAX_WIDTH,
        help=f"range image columns, at most {MAX_WIDTH} (default: the profile's)",
    )
    fov_up: float | None = option(
        None, kind=float, group=WEIGHTS, metavar="DEG", help=f"upper {_FOV}"
    )
    fov_down: float | None = option(
        None, kind=float, group=WEIGHTS, metavar="DEG", help=f"lower {_FOV}"
    )
    batch_size: int = option(
        1, kind=int, group=RUN, metavar="N", minimum=1, help="scans per network pass (default 1)"
    )
    knn: bool = option(
        True,
        kind=bool,
        group=RUN,
        negate="--no-knn",
        help="take each point's pixel class, without kNN refinement",
    )
    device: str = option(
        "auto",
        group=RUN,
        choices=DEVICES,
        help="auto picks CUDA when present (default)",
    )
    precision: str = option(
        "auto",
        group=RUN,
        choices=PRECISIONS,
        help="precision of the network's passes; auto is fp16 on CUDA and fp32 on the CPU "
        "(default; always fp32 with --backend onnxruntime)",
    )
    backend: str = option(
        "torch",
        group=RUN,
        choices=BACKENDS,
        help="run the network in torch (default) or in onnxruntime on its ONNX export, made "
        "once per checkpoint into $RANGERET_CACHE/onnx (else ~/.cache/rangeret/onnx); "
        "onnxruntime runs fp32 only, and on CUDA needs the onnxruntime-gpu package",
    )
    onnx: str | None = option(
        None,
        group=RUN,
        metavar="FILE.onnx",
        help="with --backend onnxruntime: run this export (`rangeret export`) rather than the "
        "cached one, once it agrees with the checkpoint, resolution, profile and batch size",
    )
    tta_flip: bool = option(
        False, kind=bool, group=RUN, help="test-time augmentation: add the mirrored view"
    )
    tta_shifts: int = option(
        0,
        kind=int,
        group=RUN,
        metavar="N",
        minimum=0,
        help="test-time augmentation: add N azimuth-rotated views",
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
            minimum, choices = f.metadata["minimum"], f.metadata["choices"]
            value = getattr(self, f.name)
            if choices is not None and value is not None and value not in choices:
                return f"{name(f.name)} must be one of {', '.join(choices)}, got {value!r}"
            if minimum is not None and value is not None and value < minimum:
                least = "not be negative" if minimum == 0 else f"be at least {minimum}"
                return f"{name(f.name)} must {least}, got {value}"
            maximum = f.metadata["maximum"]
            if maximum is not None and value is not None and value > maximum:
                return f"{name(f.name)} must be at most {maximum}, got {value}"
        if self.onnx is not None and self.backend != "onnxruntime":
            return (
                f"{name('onnx')} is an export for {name('backend')} onnxruntime: add that, or "
                f"leave {name('onnx')} out"
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


_KINDS = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def _checked(f: dataclasses.Field, value: Any, key: str) -> Any:
    """`value` for field `f` (an integer or a number may come as its text), or an
    `InferenceSpecError` naming `key`."""
    kind = f.metadata["kind"]
    if value is None and f.default is None:
        return None
    converted = _as_kind(kind, value)
    if converted is None:
        raise InferenceSpecError(f"{key} takes {_KINDS[kind]}, got {value!r}")
    return converted


def _as_kind(kind: type, value: Any) -> Any:
    """`value` as `kind`, or None when it is not one."""
    if isinstance(value, bool):
        return value if kind is bool else None
    if kind is bool:
        return None
    if kind is str:
        return value if isinstance(value, str) else None
    if isinstance(value, str):
        try:
            value = int(value) if kind is int else float(value)
        except ValueError:
            return None
    if kind is int:
        return value if isinstance(value, int) else None
    if isinstance(value, int | float) and math.isfinite(value):
        return float(value)
    return None


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
        meta = f.metadata
        if meta["kind"] is bool:
            action = "store_false" if meta["negate"] else "store_true"
            parser.add_argument(flag(f.name), dest=f.name, action=action, help=meta["help"])
            continue
        kwargs: dict[str, Any] = {"help": meta["help"], "default": f.default}
        if meta["choices"] is not None:
            kwargs["choices"] = list(meta["choices"])
        else:
            kwargs["type"] = meta["cli_type"] or meta["kind"]
        if meta["metavar"] is not None:
            kwargs["metavar"] = meta["metavar"]
        parser.add_argument(flag(f.name), dest=f.name, **kwargs)
