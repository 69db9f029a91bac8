"""The models a gateway serves: each one's name, network options, profile and checkpoint.

`ModelCatalog` is what the gateway knows of its models from checking them at start (their
weights loaded once each), whether or not they are loaded now: every request, job and page picks
one by name (`?model=`, a job's `model`), or gets the default. A plain `--checkpoint` is the one
model named `default`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from fastapi import Query

from rangeret.dataset.profiles import DatasetProfile
from rangeret.inference.spec import InferenceSpec
from service.errors import ApiError

#: The header that names the model of every scan answer.
MODEL_HEADER = "X-RangeRet-Model"
#: The `model` query of the routes that act for one model.
MODEL_QUERY = Query(
    description="the model's name (`GET /v1/models` lists them); without it, the default model",
    max_length=63,
)


@dataclass(frozen=True)
class ModelEntry:
    """One served model: its name, network options, the profile it runs with, its checkpoint's
    SHA-256 and its network's name (None where the gateway does not know them)."""

    name: str
    spec: InferenceSpec
    profile: DatasetProfile
    checkpoint_sha256: str | None = None
    network: str | None = None


@dataclass(frozen=True)
class ModelCatalog:
    """The served models by name, in the models file's order, and the default one."""

    entries: dict[str, ModelEntry]
    default: str

    def __post_init__(self) -> None:
        if self.default not in self.entries:
            raise ValueError(f"the default model {self.default!r} is not among the models")

    @classmethod
    def one(cls, entry: ModelEntry) -> ModelCatalog:
        """A catalog of one model, its default."""
        return cls({entry.name: entry}, entry.name)

    @property
    def names(self) -> list[str]:
        """The models' names, in order."""
        return list(self.entries)

    def __iter__(self) -> Iterator[ModelEntry]:
        return iter(self.entries.values())

    def __len__(self) -> int:
        return len(self.entries)

    def get(self, name: str | None = None) -> ModelEntry:
        """The model `name` (None: the default); a 404 naming the known models otherwise."""
        if name is None:
            return self.entries[self.default]
        entry = self.entries.get(name)
        if entry is None:
            raise ApiError(
                404,
                f"There is no model {name[:64]!r}; this gateway serves {', '.join(self.names)}.",
            )
        return entry

    @property
    def default_entry(self) -> ModelEntry:
        """The default model."""
        return self.entries[self.default]
