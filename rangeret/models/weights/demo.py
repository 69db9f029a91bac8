"""The bundled demo weights: trained on simulated scenes only (see `data/DEMO_WEIGHTS.md`), so
every run on them says so. SemanticKITTI's are the default; nuScenes' are the default of the
nuscenes profile. Torch-free: reports and descriptions ask about them cheaply."""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

from rangeret import DATA_DIR
from rangeret.exceptions import ModelError
from rangeret.models.weights.hub import resolve_weights
from rangeret.models.weights.registry import RegistryError, load_registry

log = logging.getLogger(__name__)

#: The file of the bundled demo weights (SemanticKITTI's).
DEMO_CHECKPOINT = DATA_DIR / "demo-weights.pt"
#: The bundled demo weights of each profile that has them.
DEMO_CHECKPOINTS = {
    "semantickitti": DEMO_CHECKPOINT,
    "nuscenes": DATA_DIR / "demo-weights-nuscenes.pt",
}


def real_weights_hint(profile: str | None = None) -> str:
    """Where real weights for `profile` (None: SemanticKITTI) come from: a published model of
    that profile, or, where none is published, a network trained on it; never another
    profile's model, which would be refused."""
    name = profile or "semantickitti"
    try:
        published = [m.name for m in load_registry().values() if m.profile == name]
    except RegistryError:
        published = []
    if published:
        return f"--checkpoint {published[0]} (`rangeret weights list`)"
    return (
        f"--checkpoint with a network trained for the {name} profile (none is published: "
        f"`rangeret train --profile {name}` makes one)"
    )


def demo_warning(profile: str | None = None) -> str:
    """The note every run on bundled demo weights carries, with the real weights to use instead
    for its profile."""
    return (
        "using the bundled demo weights, trained on simulated street scenes only: their labels "
        f"on real scans are not meaningful; pass {real_weights_hint(profile)}"
    )


class DemoWeightsMissing(ModelError, FileNotFoundError):
    """No --checkpoint was given and the bundled demo weights are not installed."""


def demo_checkpoint(profile: str | None = None) -> Path:
    """The bundled demo weights of a profile (None: SemanticKITTI's); a profile without any is
    `DemoWeightsMissing` naming the profiles that have them."""
    path = DEMO_CHECKPOINTS.get(profile or "semantickitti")
    if path is None:
        raise DemoWeightsMissing(
            f"no --checkpoint given, and only the {' and '.join(DEMO_CHECKPOINTS)} profiles have "
            f"bundled demo weights: pass --checkpoint with a network for the {profile} profile"
        )
    if not path.exists():
        raise DemoWeightsMissing(
            f"no --checkpoint given and the bundled demo weights {path} are missing"
        )
    return path


def resolve_checkpoint(path: str | Path | None, profile: str | None = None) -> Path:
    """The checkpoint to load: `path`, a published model's file when `path` is its registered
    name (`rangeret-kitti-657`, fetched from the cache or the hub), or the bundled demo weights
    of `profile` (announced loudly) when None."""
    if path is not None:
        return resolve_weights(path).path
    found = demo_checkpoint(profile)
    log.warning(demo_warning(profile))
    return found


def is_demo_checkpoint(sha256: str | None) -> bool:
    """Whether a checkpoint hash is that of bundled demo weights (any profile's)."""
    return bool(sha256) and any(sha256 == _demo_sha256(p) for p in DEMO_CHECKPOINTS.values())


def is_demo_path(path: str | Path) -> bool:
    """Whether a checkpoint file is one of the bundled demo weights."""
    resolved = Path(path).resolve()
    return any(p.exists() and resolved == p.resolve() for p in DEMO_CHECKPOINTS.values())


#: Each bundled demo file's SHA-256 once known: noted by the loader that read it, else read
#: once (every description of a run asks for it).
_DEMO_SHA256: dict[Path, str | None] = {}


def note_loaded(path: Path, sha256: str) -> None:
    """Remember the hash of a checkpoint a loader has just read when it is demo weights, so
    that asking about them later reads the file no second time."""
    for demo in DEMO_CHECKPOINTS.values():
        if demo.exists() and Path(path).resolve() == demo.resolve():
            _DEMO_SHA256[demo] = sha256


def _demo_sha256(demo: Path) -> str | None:
    """A bundled demo file's SHA-256 (None when it is not installed)."""
    if demo not in _DEMO_SHA256:
        _DEMO_SHA256[demo] = (
            hashlib.sha256(demo.read_bytes()).hexdigest() if demo.exists() else None
        )
    return _DEMO_SHA256[demo]
