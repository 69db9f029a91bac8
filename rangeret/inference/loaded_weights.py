"""`load_weights`: from a spec to a loaded network and the profile it runs with, in one pass.

The one path from an `InferenceSpec` to weights, for every runner: a published model's name is
resolved to its file (the cache, else the hub), the file's bytes are read once, a published
file's pin is checked on those very bytes, the network is built from them, and the profile is
settled (the checkpoint's own, or the one asked for, at the network's resolution, its class count
checked). A process loads its checkpoint from disk exactly once this way.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.exceptions import ModelError, RangeRetError
from rangeret.inference.spec import InferenceSpec
from rangeret.models.weights.checkpoint_info import CheckpointInfo
from rangeret.models.weights.demo import note_loaded, resolve_checkpoint
from rangeret.models.weights.hub import CheckpointChanged, ResolvedWeights, resolve_weights
from rangeret.models.weights.run_profile import (
    check_classes,
    default_resolution,
    profile_for_checkpoint,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoadedWeights:
    """A network in eval mode on the CPU and the profile it runs with (its class count checked),
    with where its weights came from (`info`; None for a network built in memory)."""

    network: torch.nn.Module
    profile: DatasetProfile
    info: CheckpointInfo | None = None

    @property
    def sha256(self) -> str | None:
        """The checkpoint file's SHA-256 (None for a network that came from no file)."""
        return None if self.info is None else self.info.sha256

    @property
    def model(self) -> str:
        """The network's name."""
        return self.info.name if self.info is not None else type(self.network).__name__

    @property
    def identity(self) -> WeightsIdentity:
        """What these weights are, as `identify_weights` tells it without a network."""
        return WeightsIdentity(self.sha256, self.profile, self.model)

    @classmethod
    def of_network(cls, network: torch.nn.Module, profile: DatasetProfile) -> LoadedWeights:
        """A network built or loaded by other means, checked against `profile`'s class count."""
        config = getattr(network, "config", None)
        classes = getattr(config, "num_classes", None)
        if classes is not None:
            check_classes(int(classes), profile)
        return cls(network.eval(), profile, getattr(network, "checkpoint_info", None))

    def export_onnx(self) -> Path:
        """The cached onnxruntime export of these weights, made now when missing, so that the
        workers a driver starts next load it instead of each exporting it."""
        from rangeret.inference.runtime.onnx_backend import cached_export

        return cached_export(self.network, self.profile, self.sha256)


class WeightsChanged(ModelError, RuntimeError):
    """Weights loaded for a served model that are not the ones the server checked at its start."""


@dataclass(frozen=True)
class WeightsIdentity:
    """What a model's weights are: the checkpoint's SHA-256 (None for a network that came from
    no file), the profile it runs with and the network's name; one identity for every server
    that describes models it has not loaded (the gateway's catalog, the Serve builder)."""

    sha256: str | None
    profile: DatasetProfile
    model: str

    def describe(self) -> dict[str, str | None]:
        """As a server lists it and compares it: `checkpoint_sha256`, `profile`, `network`."""
        return {
            "checkpoint_sha256": self.sha256,
            "profile": self.profile.name,
            "network": self.model,
        }

    def check_same(
        self, checked: Mapping[str, str | None], name: str, when: str, remedy: str
    ) -> None:
        """`WeightsChanged` naming the model `name` and both checkpoints unless these weights
        are those `checked` describes (`describe`), as they were `when` a server checked them."""
        if self.describe() != dict(checked):
            raise WeightsChanged(
                f"model {name}: its checkpoint is sha256 {self.sha256} ({self.model}, "
                f"{self.profile.name} profile) now and was sha256 {checked.get('checkpoint_sha256')} "
                f"({checked.get('network')}, {checked.get('profile')} profile) when {when}; {remedy}"
            )


def load_weights(
    spec: InferenceSpec,
    *,
    profile: DatasetProfile | None = None,
    expected_sha256: str | None = None,
) -> LoadedWeights:
    """The network and profile of `spec`'s weights fields, the checkpoint read once (see the
    module). `profile` stands for the profile `spec.profile` names, for callers that hold one
    already (a label configuration of their own in it); with `expected_sha256`, bytes of another
    SHA-256 are a `CheckpointChanged` before they are parsed (a server loading again what it
    checked at start)."""
    resolved = replace(_resolved(spec, profile), expected_sha256=expected_sha256)
    network = resolved.network(default_resolution=default_resolution(resolved.profile))
    info = network.checkpoint_info
    note_loaded(resolved.path, info.sha256)
    settled = profile_for_checkpoint(
        info, requested=resolved.profile, fov_up=spec.fov_up, fov_down=spec.fov_down
    )
    log.debug("loaded %s (sha256 %s) for the %s profile", info.path, info.sha256[:12], settled.name)
    return LoadedWeights(network, settled, info)


def load_checked_weights(
    spec: InferenceSpec,
    sha256: str | None,
    who: str,
    when: str,
    remedy: str,
    *,
    profile: DatasetProfile | None = None,
) -> LoadedWeights:
    """`load_weights` of a checkpoint read before (by a server at its start, by a job's driver)
    whose bytes must still have `sha256` (None: any): other bytes are a `WeightsChanged`,
    "WHO: PATH is now ... not the checkpoint of sha256 ... read WHEN; REMEDY", before they are
    parsed."""
    try:
        return load_weights(spec, profile=profile, expected_sha256=sha256)
    except CheckpointChanged as exc:
        raise WeightsChanged(f"{who}: {exc} {when}; {remedy}") from exc


class RefusalLog:
    """Why each served model could not be loaded again, each new reason logged once (a request
    for it fails the same way until the server restarts)."""

    def __init__(self, logger: logging.Logger) -> None:
        self.logger = logger
        self.reasons: dict[str, str] = {}

    def note(self, name: str, exc: RangeRetError) -> str:
        """The one-line reason of `exc`, logged when it is new for the model `name`."""
        reason = exc.summary()
        if self.reasons.get(name) != reason:
            self.reasons[name] = reason
            self.logger.error("model %s cannot be loaded again: %s", name, reason)
        return reason


def identify_weights(spec: InferenceSpec) -> WeightsIdentity:
    """The identity of `spec`'s weights, the checkpoint read once and checked as `load_weights`
    checks it (pin, profile, class count), its tensors not loaded into a network."""
    resolved = _resolved(spec, None)
    content = resolved.checkpoint(default_resolution=default_resolution(resolved.profile))
    note_loaded(resolved.path, content.info.sha256)
    settled = profile_for_checkpoint(
        content.info, requested=resolved.profile, fov_up=spec.fov_up, fov_down=spec.fov_down
    )
    return WeightsIdentity(content.info.sha256, settled, content.info.name)


def _resolved(spec: InferenceSpec, profile: DatasetProfile | None) -> ResolvedWeights:
    """Where `spec`'s weights are and how to load them (`profile`, else the one it names)."""
    requested = profile if profile is not None else _requested_profile(spec.profile)
    path = (
        resolve_checkpoint(None, requested.name if requested is not None else None)
        if spec.checkpoint is None
        else spec.checkpoint
    )
    return resolve_weights(path, requested, spec.model, spec.height, spec.width)


def _requested_profile(name: str | None) -> DatasetProfile | None:
    """The profile a spec names, or None to let the checkpoint choose."""
    return load_profile(name) if name else None
