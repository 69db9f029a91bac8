"""A run folder's files, the resume state and the random states it restores.

`last.state.pt` holds what an exact resume needs beyond the weights: the model, optimiser,
scheduler and gradient-scaler states, epoch, step, the running sums of the current epoch and the
random states of python, numpy and torch. It is plain data and tensors (loads with
weights_only=True). A resumed run must agree with the stored `TrainConfig` on every field but
`RUNTIME_FIELDS` (`read_state` checks), and a folder that already holds a run is only continued
with resume on (`check_run_folder`). `run_record` is what every checkpoint records of the run,
`label_set` the classes it was trained for, and `better_epoch` decides which epoch best.pt holds.
"""

from __future__ import annotations

import dataclasses
import random
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rangeret.dataset.profiles import DatasetProfile, profile_of_record
from rangeret.exceptions import InputError
from rangeret.io.atomic import atomic_path
from rangeret.training.config import TrainConfig
from rangeret.training.schedule import OPTIMIZERS, SCHEDULE_NAMES

LAST = "last.pt"
BEST = "best.pt"
STATE = "last.state.pt"
STEPS_CSV = "steps.csv"
METRICS_CSV = "metrics.csv"
CURVES_PNG = "curves.png"
STATE_FORMAT = "rangeret-train-state"
STATE_VERSION = 1


class TrainingStateError(InputError, ValueError):
    """A training state that cannot be resumed, or an output folder that already holds a run."""


class TrainingStateMissing(InputError, FileNotFoundError):
    """--resume names an output folder without a training state."""


def seed_everything(seed: int) -> None:
    """Seed python's, numpy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed % (1 << 32))
    torch.manual_seed(seed)


def rng_state() -> dict[str, Any]:
    """The global random states of python, numpy and torch (and CUDA), as plain data and tensors."""
    version, internal, gauss = random.getstate()
    name, keys, pos, has_gauss, cached = np.random.get_state()
    state: dict[str, Any] = {
        "python": [version, list(internal), gauss],
        "numpy": [name, keys.tolist(), int(pos), int(has_gauss), float(cached)],
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: Mapping[str, Any]) -> None:
    """Restore what `rng_state` returned."""
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_atomic(payload: Any, path: Path) -> None:
    """torch.save `payload` to `path` atomically."""
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def check_run_folder(out: Path, resume: bool) -> Path:
    """The resume state's path in `out`, checked against `resume`: a run to continue must have
    one (TrainingStateMissing), a new run must not find one (TrainingStateError), so no run is overwritten."""
    state = out / STATE
    if resume and not state.exists():
        raise TrainingStateMissing(f"cannot resume: {state} does not exist")
    if not resume and state.exists():
        raise TrainingStateError(
            f"{out} already holds a training run ({STATE}): pass --resume to continue it, or choose another folder"
        )
    return state


def read_state(path: Path, config: TrainConfig, profile: DatasetProfile) -> dict[str, Any]:
    """The resume state at `path`, checked against the run that continues it: same profile
    (states from before profiles were SemanticKITTI's) and same settings but `RUNTIME_FIELDS`.

    The precision is compared as resolved (the trainer records fp16, fp32 or bf16); `auto` on
    either side (a state from before precisions were recorded, or a launcher that does not know
    its workers' device) is left to the check where both are known.
    """
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise TrainingStateError(f"{path} cannot be read as a training state: {exc}") from exc
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        raise TrainingStateError(f"{path} is not a training state written by rangeret.training")
    if state.get("format_version") != STATE_VERSION:
        raise TrainingStateError(
            f"{path} has state version {state.get('format_version')!r}; this code reads {STATE_VERSION}"
        )
    stored = TrainConfig.from_dict(state["config"])
    recorded = profile_of_record(state.get("profile"), str(path))
    if recorded.name != profile.name:
        raise TrainingStateError(
            f"cannot resume {path}: the run was started with the {recorded.name} profile and "
            f"cannot continue with the {profile.name} profile (pass --profile {stored.profile})"
        )
    if "auto" in (stored.precision, config.precision):
        config = dataclasses.replace(config, precision=stored.precision)
    changed = stored.with_projection(recorded.projection).differences(
        config.with_projection(profile.projection)
    )
    if not changed and "profile" in state and recorded.to_dict() != profile.to_dict():
        changed = [f"the {recorded.name} profile's contents changed"]
    if changed:
        raise TrainingStateError(
            f"cannot resume {path}: the run was started with other settings ({'; '.join(changed)})"
        )
    return state


def better_epoch(
    best: Mapping[str, Any] | None, metrics: Mapping[str, Any]
) -> dict[str, Any] | None:
    """The record of the epoch of `metrics` when it beats `best` (highest point mIoU after kNN,
    or lowest training loss without validation), else None."""
    if "val_miou_knn" in metrics:
        name, value, better = "val_miou_knn", metrics["val_miou_knn"], max
    else:
        name, value, better = "train_loss", metrics["train_loss"], min
    if best is not None and better(value, best["value"]) == best["value"]:
        return None
    return {"metric": name, "value": value, "epoch": metrics["epoch"], "step": metrics["step"]}


def label_set(profile: DatasetProfile) -> dict[str, Any]:
    """The label set a checkpoint was trained for, as its metadata records it: the profile's name,
    its class count and class names."""
    return {
        "profile": profile.name,
        "num_classes": profile.num_classes,
        "class_names": list(profile.labels.class_names),
    }


def run_record(
    config: TrainConfig,
    *,
    losses: Sequence[str],
    world_size: int,
    train_scans: int,
    val_scans: int,
) -> dict[str, Any]:
    """What every checkpoint's metadata records of the run `config` (with its precision
    resolved): optimiser, schedule, losses, precision, ranks, scans and the whole config."""
    return {
        "optimizer": {
            "name": OPTIMIZERS[config.optimizer],
            "lr": config.lr,
            "weight_decay": config.weight_decay,
        },
        "scheduler": {
            "name": SCHEDULE_NAMES[config.schedule],
            "max_lr": config.max_lr,
            "warmup": config.warmup,
        },
        "losses": list(losses),
        "class_weighting": config.class_weighting,
        "precision": config.precision,
        "world_size": world_size,
        "train_scans": train_scans,
        "val_scans": val_scans,
        "train_config": config.to_dict(),
    }
