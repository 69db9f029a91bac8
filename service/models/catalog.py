"""The models a gateway serves: each one's name, network options, profile and checkpoint.

`ModelCatalog` is the gateway's `ModelSet` (the names in order, the default, each one's spec)
with what checking each model at start found (`WeightsIdentity`: its checkpoint's SHA-256, its
profile and its network), whether or not its network is loaded now: every request, job and page
picks one by name (`?model=`, a job's `model`), or gets the default. A plain `--checkpoint` is
the one model named `default`.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fastapi import Query

from rangeret.dataset.profiles import DatasetProfile
from rangeret.inference.model_set import ModelSet, UnknownModelError
from rangeret.inference.spec import InferenceSpec
from service.http.errors import ApiError

if TYPE_CHECKING:  # torch is imported when the gateway starts, not to build its parser
    from rangeret.inference.loaded_weights import WeightsIdentity

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

    @classmethod
    def identified(cls, name: str, spec: InferenceSpec, identity: WeightsIdentity) -> ModelEntry:
        """The model `name` of `spec`, as checking its weights identified them."""
        return cls(name, spec, identity.profile, identity.sha256, identity.model)


class ModelCatalog:
    """The served models: a `ModelSet` of their specs, and each one's entry by name."""

    def __init__(self, entries: Mapping[str, ModelEntry], default: str) -> None:
        self.models = ModelSet({name: entry.spec for name, entry in entries.items()}, default)
        self.entries = dict(entries)

    @classmethod
    def identified(
        cls, models: ModelSet, identities: Mapping[str, WeightsIdentity]
    ) -> ModelCatalog:
        """The catalog of `models`, each with the identity checking its weights found."""
        entries = {
            name: ModelEntry.identified(name, spec, identities[name]) for name, spec in models
        }
        return cls(entries, models.default)

    @classmethod
    def one(cls, entry: ModelEntry) -> ModelCatalog:
        """A catalog of one model, its default."""
        return cls({entry.name: entry}, entry.name)

    @property
    def default(self) -> str:
        """The default model's name."""
        return self.models.default

    @property
    def names(self) -> list[str]:
        """The models' names, in order."""
        return self.models.names

    def __iter__(self) -> Iterator[ModelEntry]:
        return (self.entries[name] for name in self.models.names)

    def __len__(self) -> int:
        return len(self.models)

    def get(self, name: str | None = None) -> ModelEntry:
        """The model `name` (None: the default); a 404 naming the known models otherwise."""
        try:
            return self.entries[self.models.resolve(name)]
        except UnknownModelError as exc:
            raise ApiError(
                404,
                f"There is no model {name[:64]!r}; this gateway serves {', '.join(self.names)}.",
            ) from exc

    @property
    def default_entry(self) -> ModelEntry:
        """The default model."""
        return self.entries[self.models.default]
