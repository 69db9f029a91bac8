"""Labels for one cloud in any point order, invalid points included: the step every runner of
files, bags, robot messages and the gateway's file bodies shares.

The network labels the cloud's valid points (`RecordPoints.valid`); a point with a NaN or
infinite value gets the raw id of the profile's unlabelled class and confidence 0, so the answer
holds one label per input point, in the input's order. Torch-free: the gateway spreads the
labels its network workers return with `spread_labels` without loading torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from rangeret.dataset.labels import LabelConfig
from rangeret.dataset.projection import ProjectionError
from rangeret.exceptions import InputError
from rangeret.inference.results import ScanPrediction
from rangeret.io.point_fields import PointFieldsError, RecordPoints

if TYPE_CHECKING:
    from rangeret.inference.predictor import Predictor
    from rangeret.inference.timing import StageTimes


def unlabelled_raw_id(config: LabelConfig) -> int:
    """The raw id written for points the network does not label."""
    return int(config.to_raw(np.array([config.unlabeled_class]))[0])


def problem_kind(exc: Exception) -> str:
    """The short key a cloud that could not be labelled is counted (and logged once) under: a
    message layout's own kind (`CloudMessageError.kind`), `fields`, `projection`, else `input`."""
    kind = getattr(exc, "kind", None)
    if isinstance(kind, str):
        return kind
    if isinstance(exc, PointFieldsError):
        return "fields"
    return "projection" if isinstance(exc, ProjectionError) else "input"


def spread_labels(
    valid: np.ndarray,
    labels: np.ndarray,
    confidence: np.ndarray | None,
    *,
    config: LabelConfig,
    instances: np.ndarray | None = None,
) -> ScanPrediction:
    """The labels and confidences of a cloud's valid points as one per point of the cloud (raw
    ids and confidences both set): the invalid ones get the unlabelled raw id and confidence 0
    (0 for all without confidences), and with panoptic segmentation's `instances`, no object
    (instance 0, which is also their panoptic label's instance)."""
    every = np.full(len(valid), unlabelled_raw_id(config), dtype=np.uint32)
    every[valid] = labels
    scores = np.zeros(len(valid), dtype=np.float32)
    if confidence is not None:
        scores[valid] = confidence
    objects = None
    if instances is not None:
        objects = np.zeros(len(valid), dtype=np.uint32)
        objects[valid] = instances
    return ScanPrediction(labels=every, confidence=scores, instances=objects)


def label_cloud(
    predictor: Predictor, cloud: RecordPoints, times: StageTimes | None = None
) -> ScanPrediction:
    """Raw labels and confidences for every point of `cloud` (see the module docstring).

    A projection error (a laser id outside the sensor's rows, say) propagates as the
    `ProjectionError` it is, for the caller to report against its source.
    """
    valid = cloud.valid
    panoptic = predictor.clustering is not None
    if not np.any(valid):
        none = np.empty(0, np.uint32)
        return spread_labels(
            valid, none, None, config=predictor.label_config, instances=none if panoptic else None
        )
    points = cloud.points if cloud.num_invalid == 0 else cloud.points[valid]
    (result,) = predictor.label_projections(
        [predictor.project(points, times)], times, with_confidence=True
    )
    if isinstance(result, str):  # more objects than the benchmark's panoptic label holds
        raise InputError(result)
    return spread_labels(
        valid,
        result.labels,
        result.confidence,
        config=predictor.label_config,
        instances=result.instances,
    )
