"""`CheckpointInfo`: where a loaded network's weights came from, attached to the network."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class CheckpointInfo:
    """Where a loaded network's weights came from and what was stored with them.

    `config` is the network's full configuration (`ModelConfig.to_dict()`); `published` is True for
    files without the project's metadata (label_config, projection, metadata and profile are then
    None). `profile` is the dataset profile the network was trained for (`DatasetProfile.to_dict()`),
    None in files written before profiles existed, which were all SemanticKITTI's.
    """

    path: str
    sha256: str
    name: str
    config: dict[str, Any]
    published: bool
    label_config: dict[str, Any] | None
    projection: dict[str, Any] | None
    metadata: dict[str, Any] | None
    profile: dict[str, Any] | None = None

    @property
    def parent(self) -> dict[str, Any] | None:
        """The checkpoint these weights were fine-tuned from (`rangeret train --init-from`): the
        name or path given, its file and SHA-256, as the training metadata records it; None for
        weights trained from scratch and for published files."""
        parent = (self.metadata or {}).get("parent")
        return dict(parent) if isinstance(parent, dict) else None
