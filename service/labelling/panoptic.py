"""Panoptic single scans: the objects of a scan as `rangeret predict --panoptic` finds them.

A request with `panoptic=true` is labelled by the same network with its thing classes' points
clustered into objects (`Predictor.with_clustering`), as the model's `cluster_angle` and
`min_cluster_points` say. Its labels are the panoptic labels of the model's benchmark
(SemanticKITTI: `instance << 16 | raw id`, uint32; nuScenes-panoptic: `1000 * class +
instance`, uint16), and its objects the scan-unique instance ids (0 for stuff). A model whose
profile names no thing class has no objects to find: its refusal is one sentence.
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING

import numpy as np

from rangeret.dataset.profiles import DatasetProfile
from rangeret.inference.settings import ClusterSettings
from rangeret.inference.spec import InferenceSpec

if TYPE_CHECKING:
    from rangeret.inference.scan_worker import ScanWorker

#: Answer header: how many objects a panoptic answer's scan holds.
INSTANCES_HEADER = "X-RangeRet-Instances"


def model_clustering(spec: InferenceSpec) -> ClusterSettings:
    """How a model finds objects when a request or a job asks for them: its spec's
    `cluster_angle` and `min_cluster_points` (the defaults of `rangeret predict --panoptic`)."""
    return ClusterSettings(spec.cluster_angle, spec.min_cluster_points)


def panoptic_refusal(profile: DatasetProfile, model: str) -> str | None:
    """Why the model `model` of `profile` cannot find objects (its profile names no thing
    class), as one sentence; None where it can."""
    if profile.panoptic_refusal() is None:
        return None
    return (
        f"The model {model} runs with the {profile.name} profile, which names no thing classes, "
        "so it has no objects to find: leave panoptic out, or use a model whose profile names "
        "its things."
    )


def clustered_worker(worker: ScanWorker, clustering: ClusterSettings) -> ScanWorker:
    """The same scan worker (network, warm-up and lock shared) whose scans' thing points are
    clustered into objects as `clustering` says."""
    other = copy.copy(worker)
    other.predictor = worker.predictor.with_clustering(clustering)
    other.without_knn = worker.without_knn.with_clustering(clustering)
    return other


def panoptic_dtype(profile: DatasetProfile) -> np.dtype:
    """The little-endian width of the profile's panoptic labels, as its benchmark's panoptic
    files hold them: uint32 in SemanticKITTI's `.label` files, uint16 in nuScenes-panoptic's
    `.npz` files."""
    return profile.layout.panoptic_file.dtype


def label_classes(profile: DatasetProfile, labels: np.ndarray, panoptic: bool) -> np.ndarray:
    """The training class of each label of an answer (a panoptic one's semantic part)."""
    if panoptic:
        labels = profile.layout.panoptic_encoding.semantic(labels)
    return profile.prediction_classes(labels)


def scan_objects(
    profile: DatasetProfile, classes: np.ndarray, instances: np.ndarray
) -> list[tuple[int, str, int]]:
    """Each object of a scan, by instance id: (instance, class name, points); an object's class
    is that of the most of its points."""
    things = instances > 0
    if not things.any():
        return []
    ids, inverse = np.unique(instances[things], return_inverse=True)
    num_classes = profile.labels.num_classes
    votes = np.zeros((ids.size, num_classes), dtype=np.int64)
    np.add.at(votes, (inverse, classes[things].astype(np.int64)), 1)
    names = profile.labels.class_names
    return [(int(i), names[int(votes[k].argmax())], int(votes[k].sum())) for k, i in enumerate(ids)]
