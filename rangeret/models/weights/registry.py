"""The published models by name: a registry kept as data (`data/models.yaml`).

Each name gives the model hub's repository and file, the network and its blocks, the resolution
and dataset profile it was trained for, the published mIoU, the licence as the release states it,
and the file's SHA-256 and size where they are known (never guessed). `RANGERET_REGISTRY` may
name a YAML file of more entries in the same form (a private model zoo or mirror); its names
replace built-in ones of the same name.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rangeret import DATA_DIR
from rangeret.dataset.profiles import DatasetProfile, ProfileError, load_profile
from rangeret.exceptions import ConfigError
from rangeret.io.bounded_yaml import YamlLimitError, load_yaml

BUILTIN_REGISTRY = DATA_DIR / "models.yaml"
#: A YAML file of more registry entries, read after the built-in ones.
REGISTRY_VARIABLE = "RANGERET_REGISTRY"
_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_FIELDS = (
    "repo", "file", "revision", "model", "blocks", "height", "width", "profile", "dataset",
    "miou", "license", "sha256", "size",
)  # fmt: skip


class RegistryError(ConfigError, ValueError):
    """A registry file that cannot be read, or an entry that breaks its form."""


@dataclass(frozen=True)
class PublishedModel:
    """One published checkpoint: where it lies and what it is."""

    name: str
    repo: str
    file: str
    revision: str
    model: str
    blocks: int
    height: int
    width: int
    profile: str
    dataset: str
    miou_valid: float | None
    miou_test: float | None
    license: str
    sha256: str | None
    size: int | None

    def miou_text(self) -> str:
        """The published mIoU as `val 65.7 / test 64.5` (a split without a figure is left out)."""
        parts = [
            f"{split} {value:.1f}"
            for split, value in (("val", self.miou_valid), ("test", self.miou_test))
            if value is not None
        ]
        return " / ".join(parts) or "not published"


def _entry(name: str, data: Any, source: Path) -> PublishedModel:
    """A registry entry checked for its form; `RegistryError` naming the file and field."""
    where = f"{source}: entry {name!r}"
    if not isinstance(data, dict):
        raise RegistryError(f"{where} is not a mapping of fields")
    unknown = sorted(set(data) - set(_FIELDS))
    if unknown:
        raise RegistryError(f"{where} has unknown field(s) {', '.join(unknown)}")
    missing = [f for f in ("repo", "file", "model", "profile") if not data.get(f)]
    if missing:
        raise RegistryError(f"{where} lacks {', '.join(missing)}")
    sha256 = data.get("sha256")
    if sha256 is not None and not _SHA256.match(str(sha256)):
        raise RegistryError(f"{where} has a sha256 that is not 64 lower-case hex digits")
    miou = data.get("miou") or {}
    try:
        return PublishedModel(
            name=name,
            repo=str(data["repo"]),
            file=str(data["file"]),
            revision=str(data.get("revision") or "main"),
            model=str(data["model"]),
            blocks=int(data.get("blocks") or 0),
            height=int(data.get("height") or 0),
            width=int(data.get("width") or 0),
            profile=str(data["profile"]),
            dataset=str(data.get("dataset") or data["profile"]),
            miou_valid=None if miou.get("valid") is None else float(miou["valid"]),
            miou_test=None if miou.get("test") is None else float(miou["test"]),
            license=str(data.get("license") or "not stated"),
            sha256=None if sha256 is None else str(sha256),
            size=None if data.get("size") is None else int(data["size"]),
        )
    except (TypeError, ValueError, AttributeError) as exc:
        raise RegistryError(f"{where} has a field of the wrong type ({exc})") from exc


def _read(path: Path) -> dict[str, PublishedModel]:
    try:
        data = load_yaml(path)
    except (OSError, YamlLimitError) as exc:
        raise RegistryError(f"cannot read the model registry {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise RegistryError(f"{path} is not a mapping of model names to entries")
    return {str(name): _entry(str(name), entry, path) for name, entry in data.items()}


def load_registry() -> dict[str, PublishedModel]:
    """Every registered model by name: the built-in ones, then those of `RANGERET_REGISTRY`."""
    models = _read(BUILTIN_REGISTRY)
    extra = os.environ.get(REGISTRY_VARIABLE, "").strip()
    if extra:
        models.update(_read(Path(extra).expanduser()))
    return models


def lookup(name: str) -> PublishedModel | None:
    """The registered model called `name`, or None when no entry has that name."""
    return load_registry().get(name)


def profile_for_published(
    model: PublishedModel, requested: DatasetProfile | None
) -> DatasetProfile:
    """The profile a published model runs with: its own, or `requested` when that is the same
    profile (a ValueError naming both when it is another)."""
    if requested is None:
        return load_profile(model.profile)
    if requested.name != model.profile:
        raise ProfileError(
            f"{model.name} was trained for the {model.profile} profile and cannot run with the "
            f"{requested.name} profile; leave --profile out or pass --profile {model.profile}"
        )
    return requested
