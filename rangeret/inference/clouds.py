"""Labels for one cloud in any point order, invalid points included: the step every runner of
files, bags and robot messages shares.

The network labels the cloud's valid points (`RecordPoints.valid`); a point with a NaN or
infinite value gets the raw id of the profile's unlabelled class and confidence 0, so the answer
holds one label per input point, in the input's order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rangeret.inference.predictor import Predictor
from rangeret.inference.timing import StageTimes
from rangeret.io.point_fields import RecordPoints


@dataclass(frozen=True)
class CloudLabels:
    """Raw ids (uint32) and confidences (float32, 0..1), one per point of the cloud."""

    labels: np.ndarray
    confidence: np.ndarray


def unlabelled_raw_id(predictor: Predictor) -> int:
    """The raw id written for points the network does not label."""
    config = predictor.label_config
    return int(config.to_raw(np.array([config.unlabeled_class]))[0])


def label_cloud(
    predictor: Predictor, cloud: RecordPoints, times: StageTimes | None = None
) -> CloudLabels:
    """Raw labels and confidences for every point of `cloud` (see the module docstring).

    A projection error (a laser id outside the sensor's rows, say) propagates as the
    `ProjectionError` it is, for the caller to report against its source.
    """
    n = cloud.num_points
    labels = np.full(n, unlabelled_raw_id(predictor), dtype=np.uint32)
    confidence = np.zeros(n, dtype=np.float32)
    valid = cloud.valid
    if np.any(valid):
        points = cloud.points if cloud.num_invalid == 0 else cloud.points[valid]
        (result,) = predictor.finish_batch(
            [predictor.project(points, times)], times=times, with_confidence=True
        )
        labels[valid] = result.labels
        confidence[valid] = result.confidence
    return CloudLabels(labels=labels, confidence=confidence)
