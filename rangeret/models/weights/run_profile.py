"""The dataset profile a loaded checkpoint runs with: the one it records (project files) or the
one asked for (published files), at the network's resolution, with its class count checked."""

from __future__ import annotations

from dataclasses import replace

from rangeret.dataset.labels import parse_label_config
from rangeret.dataset.profiles import DatasetProfile, legacy_profile, profile_of_record
from rangeret.dataset.projection import ProjectionConfig
from rangeret.models.weights.checkpoint import CheckpointError
from rangeret.models.weights.checkpoint_info import CheckpointInfo


def profile_for_checkpoint(
    info: CheckpointInfo,
    *,
    requested: DatasetProfile | None,
    fov_up: float | None = None,
    fov_down: float | None = None,
) -> DatasetProfile:
    """The profile a loaded network runs with, its projection at the network's resolution.

    The project's own files give their recorded profile (files from before profiles: the
    `semantickitti` profile with the stored projection and labels); a `requested` profile of
    another name is a CheckpointError naming both; None asks for the recorded one. Published files
    record none: they take `requested`, else SemanticKITTI's (`legacy_profile`). A class count that differs from the profile's is a CheckpointError naming both.
    """
    if info.published:
        profile = requested or legacy_profile()
        projection = profile.projection
    else:
        profile = _recorded_profile(info)
        if requested is not None and requested.name != profile.name:
            raise CheckpointError(
                f"{info.path} was trained for the {profile.name} profile and cannot run with the "
                f"{requested.name} profile; leave --profile out or pass --profile {profile.name}"
            )
        projection = _stored_projection(info.projection) or profile.projection
    projection = replace(projection, height=info.config["height"], width=info.config["width"])
    profile = replace(profile, projection=projection).with_overrides(
        fov_up=fov_up, fov_down=fov_down
    )
    check_classes(int(info.config["num_classes"]), profile, info.path)
    return profile


def check_classes(classes: int, profile: DatasetProfile, source: str | None = None) -> None:
    """A CheckpointError naming both counts unless a network of `classes` classes (from the
    file `source`, when it came from one) was made for `profile`'s labels."""
    if classes == profile.num_classes:
        return
    if source is None:
        raise CheckpointError(
            f"the network predicts {classes} classes but the {profile.name} profile has "
            f"{profile.num_classes}: it was not made for this dataset"
        )
    raise CheckpointError(
        f"{source} predicts {classes} classes but the {profile.name} profile has "
        f"{profile.num_classes}: the network was not made for this dataset "
        "(choose its profile with --profile)"
    )


def _recorded_profile(info: CheckpointInfo) -> DatasetProfile:
    """The profile a project checkpoint records; SemanticKITTI's for files from before profiles,
    with the label configuration they stored."""
    if info.profile:
        return profile_of_record(info.profile, info.path)
    profile = legacy_profile()
    if info.label_config:
        labels = parse_label_config(info.label_config, f"checkpoint {info.path}")
        profile = replace(profile, labels=labels)
    return profile


def _stored_projection(record: dict | None) -> ProjectionConfig | None:
    """The projection stored in a project checkpoint, if any."""
    if not record:
        return None
    stored = dict(record)
    for key in ("means", "stds"):
        if key in stored:
            stored[key] = tuple(stored[key])
    return ProjectionConfig(**stored)


def default_resolution(profile: DatasetProfile | None) -> tuple[int, int]:
    """The resolution a published file runs at: the requested profile's, else SemanticKITTI's
    (published files record none)."""
    base = (profile or legacy_profile()).projection
    return base.height, base.width
