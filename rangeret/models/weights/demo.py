"""The bundled demo weights: trained on simulated scenes only (see `data/DEMO_WEIGHTS.md`), so
every run on them says so. Torch-free: reports and descriptions ask about them cheaply."""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

from rangeret import DATA_DIR
from rangeret.exceptions import ModelError
from rangeret.models.weights.hub import resolve_weights

log = logging.getLogger(__name__)

#: The file of the bundled demo weights.
DEMO_CHECKPOINT = DATA_DIR / "demo-weights.pt"
DEMO_WARNING = (
    "using the bundled demo weights, trained on simulated street scenes only: their labels on "
    "real scans are not meaningful; pass --checkpoint with real weights such as "
    "rangeret-kitti-657 (`rangeret weights list`)"
)


class DemoWeightsMissing(ModelError, FileNotFoundError):
    """No --checkpoint was given and the bundled demo weights are not installed."""


def resolve_checkpoint(path: str | Path | None) -> Path:
    """The checkpoint to load: `path`, a published model's file when `path` is its registered
    name (`rangeret-kitti-657`, fetched from the cache or the hub), or the bundled demo weights
    (announced loudly) when None."""
    if path is not None:
        return resolve_weights(path).path
    if not DEMO_CHECKPOINT.exists():
        raise DemoWeightsMissing(
            f"no --checkpoint given and the bundled demo weights {DEMO_CHECKPOINT} are missing"
        )
    log.warning(DEMO_WARNING)
    return DEMO_CHECKPOINT


def is_demo_checkpoint(sha256: str | None) -> bool:
    """Whether a checkpoint hash is that of the bundled demo weights."""
    return bool(sha256) and sha256 == _demo_sha256()


#: The bundled demo weights' SHA-256 once known: noted by the loader that read them, else read
#: once (every description of a run asks for it).
_DEMO_SHA256: dict[str, str | None] = {}


def note_loaded(path: Path, sha256: str) -> None:
    """Remember the hash of a checkpoint a loader has just read when it is the demo weights, so
    that asking about them later reads the file no second time."""
    if DEMO_CHECKPOINT.exists() and Path(path).resolve() == DEMO_CHECKPOINT.resolve():
        _DEMO_SHA256["sha256"] = sha256


def _demo_sha256() -> str | None:
    """The bundled demo weights' SHA-256 (None when they are not installed)."""
    if "sha256" not in _DEMO_SHA256:
        _DEMO_SHA256["sha256"] = (
            hashlib.sha256(DEMO_CHECKPOINT.read_bytes()).hexdigest()
            if DEMO_CHECKPOINT.exists()
            else None
        )
    return _DEMO_SHA256["sha256"]
