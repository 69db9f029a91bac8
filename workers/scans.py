"""Labelling a batch of single scans with one network: what a Serve replica and the gateway's
in-process mode both run, so both give the labels `rangeret predict` gives.

`ScanWorker` holds a predictor built from a spec (and one without kNN that shares its network),
warmed up before its first scan. A scan that cannot be projected gets the reason instead of
labels, so it never fails the other scans of its batch.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rangeret.dataset.projection import Projection
from rangeret.inference.predictor import PredictorSpec
from workers.pipeline import warm_up


@dataclass
class LabelledScan:
    """One labelled scan: raw labels (uint32, one per point) and, when asked, each point's
    confidence in its label (float32)."""

    labels: np.ndarray
    confidence: np.ndarray | None = None


class ScanWorker:
    """A network that labels batches of single scans, with or without kNN per request."""

    def __init__(self, spec: PredictorSpec, cpus: float = 1.0) -> None:
        import torch

        torch.set_num_threads(max(1, math.ceil(cpus)))
        self.spec_predictor = spec.build()
        knn = self.spec_predictor.knn
        self.without_knn = self.spec_predictor.with_knn(None)
        if knn is None:
            self.spec_predictor = self.without_knn
        self.warm_up_seconds = warm_up(self.spec_predictor)

    @property
    def profile(self):
        """The dataset profile the network runs with (point record, labels)."""
        return self.spec_predictor.profile

    def info(self) -> dict:
        """Who this worker is: process, torch threads, device and model, for health checks."""
        import torch

        return {
            "pid": os.getpid(),
            "threads": torch.get_num_threads(),
            **self.spec_predictor.describe(),
        }

    def predict(
        self, scans: Sequence[np.ndarray], knn: bool = True, confidence: bool = False
    ) -> list[LabelledScan | str]:
        """Each scan of a batch of the profile's point records labelled (with its points'
        confidences when asked), or the reason it cannot be projected."""
        predictor = self.spec_predictor if knn else self.without_knn
        projections: list[Projection] = []
        rejected: dict[int, str] = {}
        for i, scan in enumerate(scans):
            try:
                projections.append(predictor.project(scan))
            except ValueError as exc:
                rejected[i] = str(exc)
        done = iter(
            [
                LabelledScan(r.labels, r.confidence)
                for r in predictor.finish_batch(projections, with_confidence=confidence)
            ]
            if projections
            else []
        )
        return [rejected[i] if i in rejected else next(done) for i in range(len(scans))]
