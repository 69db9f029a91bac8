"""Several networks by name: a models file, one `InferenceSpec` per name and which is the default.

A models file is YAML (or the same mapping given as a Serve application's arguments):

    default: kitti
    models:
      kitti: {checkpoint: rangeret-kitti-657}
      panda: {checkpoint: /models/panda.pt, profile: pandaset}

Each entry holds network options by `InferenceSpec` field name over a base spec (the command
line's other network options), except the batch size, which is the server's. `default` may be
left out when there is one model. A name matches `NAME_PATTERN`, since it goes into a query, a
header, a metric label and a Ray submission id. A plain spec is the one model named `default`.
Torch-free.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rangeret.exceptions import ConfigError
from rangeret.inference.spec import InferenceSpec, InferenceSpecError

#: What a model's name may be: lower-case letters and digits, then also '.', '_' and '-'.
NAME_PATTERN = re.compile(r"[a-z0-9][a-z0-9._-]{0,62}")
#: The name of the one model a plain `--checkpoint` serves.
DEFAULT_NAME = "default"
#: Options an entry may not set: the server's, not a model's.
SERVER_OPTIONS = ("batch_size",)


class ModelsFileError(ConfigError, ValueError):
    """A models file (or mapping) that cannot be used: one sentence naming it and the field."""


class UnknownModelError(ConfigError, KeyError):
    """A name no model has; the message lists the known ones."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class ModelSet:
    """The models a server offers, by name in the file's order, and its default one."""

    specs: Mapping[str, InferenceSpec]
    default: str

    def __post_init__(self) -> None:
        if self.default not in self.specs:
            raise ModelsFileError(f"the default model {self.default!r} is not among the models")

    @classmethod
    def single(cls, spec: InferenceSpec) -> ModelSet:
        """One model, `default`: what a plain `--checkpoint` serves."""
        return cls({DEFAULT_NAME: spec}, DEFAULT_NAME)

    @property
    def names(self) -> list[str]:
        """The models' names, in order."""
        return list(self.specs)

    def __iter__(self) -> Iterator[tuple[str, InferenceSpec]]:
        return iter(self.specs.items())

    def __len__(self) -> int:
        return len(self.specs)

    def resolve(self, name: str | None) -> str:
        """`name`, or the default for None; an `UnknownModelError` listing the names otherwise."""
        if name is None:
            return self.default
        if name not in self.specs:
            raise UnknownModelError(
                f"there is no model {name!r}; the models are {', '.join(self.names)}"
            )
        return name

    def spec(self, name: str | None = None) -> InferenceSpec:
        """The spec of the model `name` (None: the default)."""
        return self.specs[self.resolve(name)]

    def to_mapping(self) -> dict[str, Any]:
        """The models file's mapping (each entry's options that differ from the defaults, but the
        server's), which `from_mapping` over the same base reads back to an equal set."""
        return {
            "default": self.default,
            "models": {
                name: {k: v for k, v in spec.to_mapping().items() if k not in SERVER_OPTIONS}
                for name, spec in self.specs.items()
            },
        }

    @classmethod
    def from_mapping(
        cls, data: Any, base: InferenceSpec | None = None, *, source: str = "models"
    ) -> ModelSet:
        """The models of a models file's mapping over `base` (the server's other options);
        anything wrong is one `ModelsFileError` naming `source` and the field."""
        base = base or InferenceSpec()
        if not isinstance(data, Mapping):
            raise ModelsFileError(
                f"{source}: must be a mapping with `models` (and `default`), got "
                f"{type(data).__name__}"
            )
        extra = sorted(str(k) for k in data if k not in ("default", "models"))
        if extra:
            raise ModelsFileError(
                f"{source}: {extra[0]}: is not a field (expected: default, models)"
            )
        models = data.get("models")
        if not isinstance(models, Mapping) or not models:
            raise ModelsFileError(f"{source}: models: must map each model's name to its options")
        specs = {}
        for name, options in models.items():
            specs[_checked_name(name, source)] = _entry(name, options, base, source)
        default = data.get("default")
        if default is None:
            if len(specs) > 1:
                raise ModelsFileError(
                    f"{source}: default: is missing; name one of {', '.join(specs)}"
                )
            default = next(iter(specs))
        elif not isinstance(default, str) or default not in specs:
            raise ModelsFileError(
                f"{source}: default: {default!r} is not one of the models ({', '.join(specs)})"
            )
        return cls(specs, default)


def load_models_file(path: Path | str, base: InferenceSpec | None = None) -> ModelSet:
    """The models of the YAML file `path` over `base`; a `ModelsFileError` naming the file."""
    from rangeret.io.bounded_yaml import read_yaml

    data = read_yaml(path, "the models file", ModelsFileError)
    return ModelSet.from_mapping(data, base, source=str(path))


def _checked_name(name: Any, source: str) -> str:
    """A model's name once it matches `NAME_PATTERN`."""
    if not isinstance(name, str) or NAME_PATTERN.fullmatch(name) is None:
        raise ModelsFileError(
            f"{source}: models: {name!r} is not a model name (lower-case letters and digits, "
            "then also '.', '_' or '-', at most 63 characters)"
        )
    return name


def _entry(name: str, options: Any, base: InferenceSpec, source: str) -> InferenceSpec:
    """The spec of one entry: `base` with the entry's options in place of its own."""
    if options is None:
        options = {}
    if not isinstance(options, Mapping):
        raise ModelsFileError(
            f"{source}: models.{name}: must be a mapping of network options, got "
            f"{type(options).__name__}"
        )
    for key in SERVER_OPTIONS:
        if key in options:
            raise ModelsFileError(
                f"{source}: models.{name}.{key}: is the server's setting, not a model's"
            )
    try:
        return InferenceSpec.from_mapping(
            {**base.to_mapping(), **options}, where=f" of models.{name} in {source}"
        )
    except InferenceSpecError as exc:
        raise ModelsFileError(str(exc)) from exc
