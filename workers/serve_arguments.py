"""The arguments of the Serve application (`workers.serve_app:build_app`), read and checked before
any replica starts.

One model: the fields of `rangeret.inference.spec.InferenceSpec` by name, as `rangeret serve`
takes them as options; it is the model named `default`. Several models: `models` is either the
mapping of a models file (each name to its network options, `rangeret.inference.model_set`)
with `default` beside it, or the path of a models file, which names its own default; the other
network options are defaults an entry overrides. Besides them: `batch_size` (the application's,
not a model's), `batch_wait_ms`, the longest a request waits for others to fill its batch, and
`max_num_models_per_replica`, the most networks one replica keeps loaded (default: every model).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from rangeret.dataset.fields import is_int, is_number
from rangeret.inference.model_set import (
    ModelSet,
    ModelsFileError,
    load_models_file,
)
from rangeret.inference.spec import InferenceSpec, InferenceSpecError

#: Where the application's arguments are, in the sentences that name one.
WHERE = " of the rangeret Serve application"
#: The longest a request waits for others to fill its batch unless `batch_wait_ms` says otherwise.
DEFAULT_BATCH_WAIT_MS = 10.0
#: The application's own arguments besides the network options.
APP_ARGUMENTS = ("batch_wait_ms", "models", "default", "max_num_models_per_replica")


@dataclass(frozen=True)
class AppArguments:
    """The application's checked arguments: its models, the batch size and wait of every
    replica, and how many networks a replica keeps loaded."""

    models: ModelSet
    batch_size: int
    batch_wait_ms: float
    max_per_replica: int


def read_arguments(args: Mapping[str, object]) -> AppArguments:
    """The checked arguments; anything unknown or bad is one `ValueError` naming it."""
    values = {k: v for k, v in args.items() if k not in APP_ARGUMENTS}
    try:
        base = InferenceSpec.from_mapping(values, where=WHERE)
    except InferenceSpecError as exc:
        raise ValueError(str(exc)) from exc
    models = _models(args, base)
    return AppArguments(
        models,
        base.batch_size,
        _batch_wait_ms(args.get("batch_wait_ms", DEFAULT_BATCH_WAIT_MS)),
        _max_per_replica(args.get("max_num_models_per_replica"), len(models)),
    )


def _models(args: Mapping[str, object], base: InferenceSpec) -> ModelSet:
    """The models the arguments name: `models` (a mapping or a models file's path) with
    `default`, or the one model `default` of the network options."""
    given = args.get("models")
    try:
        if given is None:
            for name in ("default", "max_num_models_per_replica"):
                if name in args:
                    raise ValueError(f"{name}{WHERE} goes with models, which is not given")
            return ModelSet.single(base)
        if isinstance(given, str):
            if "default" in args:
                raise ValueError(
                    f"default{WHERE} is the models file's own: name it in {given}, not beside it"
                )
            return load_models_file(given, base)
        mapping = {"models": given, **({"default": args["default"]} if "default" in args else {})}
        return ModelSet.from_mapping(mapping, base, source=f"the models{WHERE}")
    except ModelsFileError as exc:
        raise ValueError(str(exc)) from exc


def _batch_wait_ms(wait: object) -> float:
    """`batch_wait_ms` once it is a number of milliseconds, zero or more."""
    if not is_number(wait):
        raise ValueError(f"batch_wait_ms{WHERE} takes a number, got {wait!r}")
    if wait < 0:
        raise ValueError(f"batch_wait_ms must not be negative, got {wait:g}")
    return float(wait)


def _max_per_replica(value: object, models: int) -> int:
    """`max_num_models_per_replica` once it is a whole number from 1 (default: every model)."""
    if value is None:
        return models
    if not is_int(value) or value < 1:
        raise ValueError(
            f"max_num_models_per_replica{WHERE} takes a whole number from 1, got {value!r}"
        )
    return value
