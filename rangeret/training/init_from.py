"""Starting a run from a checkpoint's weights: `rangeret train --init-from CHECKPOINT`.

The parent is a checkpoint file (the project's own or a published one) or a published model's
name of `rangeret weights list` (its file from the hub cache, else downloaded, its pin checked).
Only its weights are taken, not its profile: the run trains for its own `--profile`. Its network
settles the run's (`settle_network`): the model and every override come from the parent, and
`--model` and `--override` may only repeat them; the class count and the resolution are the
run's. No tensor of either network depends on the resolution (the decay and the rotary angles
are computed from the patch grid at run time), so weights made at any resolution fit; a tensor
that did would be refused by name like any other that does not fit.

`initialise` loads every tensor of the parent whose name and shape match into the freshly built
network. Where the run's class count differs from the parent's, the head's tensors that do not
fit (its last linear layer) keep the initialisation `build_model` gave them and are the run's new
tensors; any other tensor that does not fit, is missing from the parent or is left over in it is
a `CheckpointError` naming it. `Freeze` keeps the loaded tensors as they are (no gradient, so no
AdamW step or weight decay, and their modules in eval mode, so no BatchNorm statistics) during
the run's first `freeze_backbone_steps` steps. `FineTuning` is what the trainer holds of both.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from rangeret.dataset.profiles import DatasetProfile
from rangeret.exceptions import InputFileMissing
from rangeret.models import RangeRet, build_model
from rangeret.models.configs import OVERRIDES, ModelConfig, resolve_config
from rangeret.models.weights.checkpoint import (
    CheckpointContent,
    CheckpointError,
)
from rangeret.models.weights.hub import published_name, resolve_weights
from rangeret.training.config import TrainConfig, TrainConfigError
from rangeret.training.state import TrainingStateError

log = logging.getLogger("rangeret.training")

#: The prefix of the classification head's tensors, the only ones a new class count may replace.
HEAD = "head."
_LISTED = 8


@dataclass(frozen=True)
class Parent:
    """The checkpoint a run starts from: `source` as the run names it (a published model's name or
    an absolute path) and what its file holds."""

    source: str
    content: CheckpointContent

    @property
    def config(self) -> ModelConfig:
        """The parent's network configuration (its class count and resolution included)."""
        return self.content.config

    def record(self) -> dict[str, Any]:
        """What checkpoints record of the parent: the name or path given, its file, the SHA-256
        of the file's bytes, its network and class count, and the profile it was trained for
        (a published model's from the registry; None for a published file named by its path,
        which records none)."""
        info = self.content.info
        return {
            "source": self.source,
            "path": info.path,
            "sha256": info.sha256,
            "model": info.name,
            "num_classes": self.config.num_classes,
            "profile": (info.profile or {}).get("name") or _published_profile(self.source),
            "published": info.published,
        }


def _published_profile(source: str) -> str | None:
    """The profile the registry gives a published model named by `source`; None for a file,
    whose bytes record none."""
    model = published_name(source)
    return None if model is None else model.profile


def read_parent(source: str, overrides: Mapping[str, Any] | None = None) -> Parent:
    """The checkpoint `source` names (a file, or a published model's name whose file comes from
    the hub cache or the hub, its pin checked on the bytes read), read once, not loaded yet.

    A published file records only what its tensors' shapes tell (the network, blocks, width,
    patch size, classes); `overrides` give the switches they cannot tell (heads, decay, ...),
    as for loading it anywhere else. The project's own files record everything.
    """
    resolved = resolve_weights(source)
    if not resolved.path.is_file():
        raise InputFileMissing(
            errno.ENOENT,
            "--init-from names neither a checkpoint file nor a published model "
            "(`rangeret weights list` names those)",
            str(resolved.path),
        )
    return Parent(source, resolved.checkpoint(overrides=overrides))


def settle_network(
    parent: Parent, model: str | None, overrides: Mapping[str, Any]
) -> dict[str, Any]:
    """The `model` and `model_overrides` settings of a run that starts from `parent`: its network's.
    A `model` or override given must repeat the parent's, else a TrainConfigError naming the
    option and both values."""
    recorded = parent.config
    if model is not None and model != recorded.name:
        raise TrainConfigError(
            f"--model {model} contradicts --init-from {parent.source}, whose network is "
            f"{recorded.name}: leave --model out or give --model {recorded.name}"
        )
    for name, value in overrides.items():
        if name not in OVERRIDES:
            raise TrainConfigError(
                f"--override {name} is not a switch of the network; accepted: {', '.join(OVERRIDES)}"
            )
        given, theirs = _comparable(name, value), getattr(recorded, name)
        if given != theirs:
            raise TrainConfigError(
                f"--override {name}={_text(given)} contradicts --init-from {parent.source}, whose "
                f"network has {name}={_text(theirs)}: leave the override out or give "
                f"{name}={_text(theirs)}"
            )
    base = resolve_config(recorded.name)
    settled = tuple(
        (name, value)
        for name, value in recorded.overrides().items()
        if getattr(base, name) != value
    )
    return {"model": recorded.name, "model_overrides": settled}


def settle_run(config: TrainConfig, profile: DatasetProfile) -> tuple[TrainConfig, Parent | None]:
    """`config` with its parent's network settled (`settle_network`), and the parent (None for a
    run from scratch); a `freeze_backbone_steps` where the parent already has the profile's
    classes, so that nothing would be new, is a TrainConfigError."""
    if config.init_from is None:
        return config, None
    parent = read_parent(config.init_from, config.overrides)
    config = dataclasses.replace(config, **settle_network(parent, config.model, config.overrides))
    if config.freeze_backbone_steps and parent.config.num_classes == profile.num_classes:
        raise TrainConfigError(
            f"--freeze-backbone-steps {config.freeze_backbone_steps} would freeze the whole "
            f"network: --init-from {parent.source} already has the {profile.name} profile's "
            f"{profile.num_classes} classes, so every tensor is loaded and none is new"
        )
    return config, parent


@dataclass(frozen=True)
class Initialisation:
    """How a network was started from its parent: the tensors loaded and the new ones."""

    parent: Parent
    loaded: tuple[str, ...]
    new: tuple[str, ...]

    def record(self) -> dict[str, Any]:
        """The parent's record (`Parent.record`) with the count of tensors loaded and the new
        ones' names, as checkpoints and the resume state keep it."""
        return {**self.parent.record(), "loaded": len(self.loaded), "new": list(self.new)}

    def describe(self, frozen_steps: int = 0) -> str:
        """One line for the log: where from, how many tensors were loaded, which are new, and
        for how many steps the loaded ones stay frozen."""
        info = self.parent.content.info
        total = len(self.loaded) + len(self.new)
        new = ", ".join(self.new) if self.new else "none"
        frozen = f"; the loaded ones stay frozen for {frozen_steps} steps" if frozen_steps else ""
        return (
            f"initialised from {self.parent.source} (sha256 {info.sha256[:12]}): "
            f"{len(self.loaded)} of {total} tensors loaded; new: {new}{frozen}"
        )


def initialise(model: RangeRet, parent: Parent) -> Initialisation:
    """Load every tensor of `parent` whose name and shape fit `model`, freshly built; where the
    class counts differ, the head's tensors that do not fit stay as built. Any other tensor that
    does not fit, is missing from the parent or is left over in it is a CheckpointError naming it."""
    theirs = parent.content.state_dict
    ours = model.state_dict()
    new_head = parent.config.num_classes != model.config.num_classes
    loaded, new, misfits = [], [], []
    for name, tensor in ours.items():
        found = theirs.get(name)
        if found is not None and tuple(found.shape) == tuple(tensor.shape):
            loaded.append(name)
        elif found is not None and new_head and name.startswith(HEAD):
            new.append(name)
        elif found is None:
            misfits.append(f"{name} is missing from it")
        else:
            misfits.append(
                f"{name} is {_shape(found)} there and {_shape(tensor)} in the network trained"
            )
    misfits += [f"{name} is not in the network trained" for name in theirs if name not in ours]
    if misfits:
        raise CheckpointError(_misfit_message(parent, model.config, misfits))
    model.load_state_dict({name: theirs[name] for name in loaded}, strict=False)
    return Initialisation(parent, tuple(loaded), tuple(new))


def check_parent(config: TrainConfig, profile: DatasetProfile) -> TrainConfig:
    """For a launcher that starts the training elsewhere: `config` with its parent's network
    settled, after checking that the parent's tensors fit the network the run trains."""
    config, parent = settle_run(config, profile)
    if parent is not None:
        projection = profile.projection
        network = build_model(
            config.model,
            projection.height,
            projection.width,
            profile.num_classes,
            **config.overrides,
        )
        initialise(network, parent)
    return config


@dataclass(frozen=True)
class Freeze:
    """The loaded tensors held as loaded for the first `steps` steps: their parameters lose their
    gradients before the optimiser steps, and the modules holding only loaded tensors stay in
    eval mode, so BatchNorm statistics do not move."""

    steps: int
    parameters: tuple[nn.Parameter, ...]
    modules: tuple[nn.Module, ...]

    @classmethod
    def of(cls, model: nn.Module, initialisation: Initialisation, steps: int) -> Freeze:
        """The freeze of `model`'s tensors that `initialisation` loaded, for `steps` steps."""
        loaded = set(initialisation.loaded)
        parameters = tuple(p for name, p in model.named_parameters() if name in loaded)
        modules = []
        for prefix, module in model.named_modules():
            own = [
                f"{prefix}.{name}" if prefix else name
                for name, _ in (
                    *module.named_parameters(recurse=False),
                    *module.named_buffers(recurse=False),
                )
            ]
            if own and all(name in loaded for name in own):
                modules.append(module)
        return cls(steps, parameters, tuple(modules))

    def active(self, step: int) -> bool:
        """Whether the step after `step` steps done is one of the frozen ones."""
        return step < self.steps

    def hold_modules(self) -> None:
        """Put the modules of loaded tensors in eval mode (after the network's `train()`)."""
        for module in self.modules:
            module.eval()

    def drop_gradients(self) -> None:
        """Remove the loaded parameters' gradients, so that the optimiser skips them."""
        for parameter in self.parameters:
            parameter.grad = None


@dataclass(frozen=True)
class FineTuning:
    """What a trainer holds of its start from a parent: the `Initialisation` and the `Freeze`;
    both None for a run from scratch, whose steps it then leaves alone."""

    initialisation: Initialisation | None = None
    freeze: Freeze | None = None

    @classmethod
    def start(
        cls, parent: Parent | None, model: RangeRet, config: TrainConfig, *, announce: bool
    ) -> FineTuning:
        """Load `parent` into the freshly built `model` (`initialise`) and set up the freeze of
        `config`'s first `freeze_backbone_steps` steps; a new run (not a resumed one) logs the
        one line of `describe` where `announce` (the main rank)."""
        if parent is None:
            return cls()
        initialisation = initialise(model, parent)
        frozen_steps = config.freeze_backbone_steps
        if announce and not config.resume:
            log.info("%s", initialisation.describe(frozen_steps))
        return cls(initialisation, Freeze.of(model, initialisation, frozen_steps))

    def hold(self, step: int) -> bool:
        """Whether the step after `step` steps done is frozen; if so, put the modules of loaded
        tensors in eval mode (call it after the network's `train()`)."""
        frozen = self.freeze is not None and self.freeze.active(step)
        if frozen:
            self.freeze.hold_modules()
        return frozen

    def drop_gradients(self, step: int) -> None:
        """After the backward pass of a frozen step: remove the loaded parameters' gradients."""
        if self.freeze is not None and self.freeze.active(step):
            self.freeze.drop_gradients()

    def record(self) -> dict[str, Any] | None:
        """The parent's record for checkpoints and the resume state, None for a run from scratch."""
        return None if self.initialisation is None else self.initialisation.record()

    def check_resume(self, path: Any, state: Mapping[str, Any]) -> None:
        """A TrainingStateError when the parent's file changed since the run in the resume state
        at `path` started from it."""
        started = (state.get("parent") or {}).get("sha256")
        now = self.record()
        if started is not None and now is not None and now["sha256"] != started:
            raise TrainingStateError(
                f"cannot resume {path}: the run started from --init-from {now['source']} with "
                f"SHA-256 {started}, and that file now has SHA-256 {now['sha256']}"
            )


def _comparable(name: str, value: Any) -> Any:
    """An override value as `ModelConfig` holds it (pairs as tuples, an int patch as a square)."""
    if isinstance(value, list):
        return tuple(value)
    if name in ("patch_size", "stride") and isinstance(value, int):
        return (value, value)
    return value


def _text(value: Any) -> str:
    """An override value as the command line writes it (a pair as AxB)."""
    if isinstance(value, tuple) and len(value) == 2:
        return f"{value[0]}x{value[1]}"
    return str(value).lower() if isinstance(value, bool) else str(value)


def _shape(tensor: torch.Tensor) -> str:
    return str(tuple(tensor.shape))


def _misfit_message(parent: Parent, config: ModelConfig, misfits: Sequence[str]) -> str:
    """The sentence for a parent whose tensors do not fit outside the head."""
    listed = "; ".join(misfits[:_LISTED]) + ("; ..." if len(misfits) > _LISTED else "")
    text = (
        f"--init-from {parent.source} does not fit the network trained outside its head "
        f"({len(misfits)} tensor(s): {listed})"
    )
    theirs = parent.config
    if not parent.content.info.published and (theirs.height, theirs.width) != (
        config.height,
        config.width,
    ):
        text += (
            f"; it was made at {theirs.height}x{theirs.width} and this run trains at "
            f"{config.height}x{config.width}: a tensor that depends on the resolution fits only "
            f"with --height {theirs.height} --width {theirs.width}"
        )
    return text
