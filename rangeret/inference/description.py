"""The plain-data description of a network and its options that logs, reports and `run.json`
carry, written once for every runner."""

from __future__ import annotations

from dataclasses import asdict

from rangeret.dataset.projection import ProjectionConfig
from rangeret.inference.settings import ClusterSettings, KnnSettings, TtaSettings
from rangeret.models.weights.demo import is_demo_checkpoint


def describe_network(
    *,
    model: str,
    checkpoint: str | None,
    sha256: str | None,
    profile: str,
    projection: ProjectionConfig,
    knn: KnnSettings | None,
    tta: TtaSettings | None,
    device: str,
    precision: str,
    backend: str = "torch",
    parent: dict | None = None,
    clustering: ClusterSettings | None = None,
) -> dict:
    """The description of a network and its options that logs, reports and `run.json` carry;
    `device` and `precision` are those used, or those asked for where the network runs
    elsewhere; `backend` is where its forward pass runs (torch or onnxruntime); `parent` is the
    checkpoint the weights were fine-tuned from (`CheckpointInfo.parent`), None if none;
    `clustering` how objects are found with panoptic segmentation (the `panoptic` key, present
    only then)."""
    return {
        "model": model,
        "checkpoint": checkpoint,
        "checkpoint_sha256": sha256,
        "demo_weights": is_demo_checkpoint(sha256),
        "parent": parent,
        "profile": profile,
        "projection": projection.to_dict(),
        "knn": asdict(knn) if knn else None,
        "tta": asdict(tta) if tta else None,
        "device": device,
        "precision": precision,
        "backend": backend,
        **({"panoptic": asdict(clustering)} if clustering else {}),
    }
