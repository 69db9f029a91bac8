"""Labelling batches of single scans with one network: what a Serve replica and the gateway's
in-process mode both run, so both give the labels `rangeret predict` gives.

A `ScanWorker` holds a predictor (and one without kNN that shares its network), warmed up before
its first scan. A batch of `ScanRequest`s may mix options: `group_by_options` splits it into one
network pass per set of equal options. A scan that cannot be projected gets the reason instead of
labels, so it never fails the other scans of its batch; a failing network pass raises.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from rangeret.dataset.profiles import DatasetProfile
from rangeret.inference.loading import project_scans
from rangeret.inference.predictor import Predictor
from rangeret.inference.results import ScanOutcome
from rangeret.inference.timing import StageTimes

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ScanRequest:
    """One scan to label (the profile's point records) and how: with kNN refinement, with each
    point's confidence."""

    points: np.ndarray
    knn: bool = True
    confidence: bool = False

    @property
    def options(self) -> tuple[bool, bool]:
        """What a request shares a network pass with: its (knn, confidence)."""
        return self.knn, self.confidence


def group_by_options(requests: Sequence[ScanRequest]) -> list[list[int]]:
    """The indices of `requests` grouped by equal options, groups in the order their first
    request came, each in order: one network pass per group."""
    groups: dict[tuple[bool, bool], list[int]] = {}
    for i, request in enumerate(requests):
        groups.setdefault(request.options, []).append(i)
    return list(groups.values())


def warm_up(predictor: Predictor) -> float:
    """Run the network once on an empty scan's range image, so that the decay tables and the
    device's kernels are built before the first real batch; the time it took is logged and
    returned, and recorded in no stage."""
    start = time.perf_counter()
    empty = predictor.project(np.zeros((0, 5), np.float32))
    predictor.logits([empty], StageTimes())
    seconds = time.perf_counter() - start
    config = predictor.projection_config
    log.info(
        "network in process %d warmed up on %s (%d x %d) in %.2f s",
        os.getpid(),
        predictor.device,
        config.height,
        config.width,
        seconds,
    )
    return seconds


def use_cpus(cpus: float) -> None:
    """Let torch's CPU kernels use `cpus` cores (rounded up), as a worker's share is sized."""
    torch.set_num_threads(max(1, math.ceil(cpus)))


class ScanWorker:
    """A network that labels batches of single scans, with or without kNN per request."""

    def __init__(self, predictor: Predictor) -> None:
        self.without_knn = predictor.with_knn(None)
        self.predictor = predictor if predictor.knn is not None else self.without_knn
        self.warm_up_seconds = warm_up(self.predictor)

    @property
    def profile(self) -> DatasetProfile:
        """The dataset profile the network runs with (point record, labels)."""
        return self.predictor.profile

    def info(self) -> dict:
        """Who this worker is: process, torch threads, device and model, for health checks."""
        return {"pid": os.getpid(), "threads": torch.get_num_threads(), **self.predictor.describe()}

    def label_requests(self, requests: Sequence[ScanRequest]) -> list[ScanOutcome]:
        """Each request's scan labelled (with its points' confidences when asked), or the reason
        it cannot be projected, in order; one network pass per set of equal options."""
        results: list[ScanOutcome] = [""] * len(requests)
        for indices in group_by_options(requests):
            knn, confidence = requests[indices[0]].options
            predictor = self.predictor if knn else self.without_knn
            scans = [requests[i].points for i in indices]
            projected = project_scans(scans, predictor.projection_config, StageTimes())
            labelled = predictor.label_projections(projected, with_confidence=confidence)
            for i, result in zip(indices, labelled, strict=True):
                results[i] = result
        return results
