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

import numpy as np

from rangeret.dataset.profiles import DatasetProfile
from rangeret.inference.loading import project_scans
from rangeret.inference.predictor import PredictorSpec
from rangeret.inference.results import ScanOutcome
from workers.stages import warm_up


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
    def profile(self) -> DatasetProfile:
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
    ) -> list[ScanOutcome]:
        """Each scan of a batch of the profile's point records labelled (with its points'
        confidences when asked), or the reason it cannot be projected. A failing network pass
        raises: it is the replica's fault, not the scans'."""
        predictor = self.spec_predictor if knn else self.without_knn
        projected = project_scans(scans, predictor.projection_config, predictor.times)
        return predictor.label_projected(projected, with_confidence=confidence)
