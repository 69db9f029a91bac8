"""What a dataset job reads of its dataset, checked against its model's profile: the `split` by the
profile's own split names, and a tables layout's `version` (nuScenes' `v1.0-mini`, say).

Each refusal is a `BadJobRequest` naming the request's field: a split the profile does not have (with the
closest name, where one is close), a `version` for a model whose datasets are folders of
sequences, a version the dataset does not hold, or none where it holds several; and a split whose
sequences the dataset does not all hold, as `rangeret predict` refuses it without
`--allow-partial`.
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from pathlib import Path

from rangeret.dataset.layout import DatasetLayoutError
from rangeret.dataset.nuscenes_tables import TableError
from service.jobs.errors import BadJobRequest
from service.models.catalog import ModelEntry
from service.schemas import DatasetJobRequest


def check_selection(request: DatasetJobRequest, model: ModelEntry) -> None:
    """`BadJobRequest` naming the field when `split` is not a split of the model's profile, or `version` is
    given for a model whose profile reads folders of sequences."""
    profile = model.profile
    try:
        profile.layout.check_version(request.version)
    except DatasetLayoutError as exc:
        raise BadJobRequest(
            f"The field 'version' is for datasets of a version's tables (nuScenes), and model "
            f"{model.name} runs with the {profile.name} profile, whose datasets are folders of "
            "sequences: leave 'version' out.",
        ) from exc
    split = request.split
    if split is not None and split not in profile.splits:
        close = difflib.get_close_matches(split, list(profile.splits), n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise BadJobRequest(
            f"The field 'split' is {split[:64]!r}, which is not a split of the {profile.name} "
            f"profile of model {model.name}: its splits are {', '.join(profile.splits)}{hint}.",
        )


def dataset_version(root: Path, version: str | None, model: ModelEntry) -> str | None:
    """The version a job of a tables profile reads under `root`: `version`, which the dataset
    must hold, else the one it holds (`BadJobRequest` naming the field otherwise); None for folder layouts."""
    try:
        held = model.profile.layout.versions(root)
    except TableError as exc:
        raise BadJobRequest("The dataset is not a folder of nuScenes tables.") from exc
    if held is None:
        return None
    if version is not None and version not in held:
        holds = f"it holds {', '.join(held)}" if held else "it holds no version's tables"
        raise BadJobRequest(
            f"The field 'version' is {version!r}, a version whose tables (scene.json) the "
            f"dataset does not hold: {holds}.",
        )
    if version is not None:
        return version
    if not held:
        raise BadJobRequest(
            "The dataset holds no nuScenes version folder (such as v1.0-mini/ with scene.json).",
        )
    if len(held) > 1:
        raise BadJobRequest(
            f"The dataset holds the versions {', '.join(held)}: choose one with the field "
            "'version'.",
        )
    return held[0]


def incomplete_split(split: str, sequences: Sequence[str], missing: Sequence[str]) -> str:
    """The answer to a split of whose `sequences` the dataset lacks `missing`."""
    shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
    held = len(sequences) - len(missing)
    return (
        f"The dataset holds {held} of the {len(sequences)} sequences of the split {split!r} "
        f"(it lacks {shown}): name those it holds with the field 'sequences'."
    )
