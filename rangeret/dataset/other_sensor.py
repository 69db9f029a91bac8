"""A network run on another sensor's data: the profile such a run reads, projects and refines with.

A checkpoint made for one profile (its classes, kNN rule and input normalisation) can label a
dataset of another sensor before it is adapted to it: the scans are read in the data profile's
record and layout and projected with its sensor (resolution, field of view, rows), the network
predicts its own classes, and a label map writes them as the data profile's raw ids. The network's
normalisation stays the one it was trained with; where the two profiles declare other
reflectance scales (`reflectance_max`), the reflectance channel's is rescaled so that a data
value means what the network learnt it to mean.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from rangeret.dataset.label_map import LabelMap, LabelMapError
from rangeret.dataset.profiles import DatasetProfile, ProfileError


def check_folder_profiles(network: DatasetProfile, data: DatasetProfile) -> None:
    """A ProfileError unless both profiles read folders of sequences and the network's writes
    raw ids (a dataset of tables, such as nuScenes, is not run on another sensor yet)."""
    for role, profile in (("network's", network), ("data's", data)):
        if profile.layout.folders is None:
            raise ProfileError(
                f"the {role} profile {profile.name} reads a version's tables; running a network "
                "on another sensor's data takes folder-layout profiles"
            )
    if network.benchmark.predictions != "raw":
        raise ProfileError(
            f"the network's profile {network.name} writes its classes, not raw ids, so a label "
            "map cannot translate them"
        )


def profile_for_data(network: DatasetProfile, data: DatasetProfile) -> DatasetProfile:
    """The profile of a run of a network made for `network` on a dataset of `data`: `data`'s
    sensor, record, layout and splits; `network`'s classes, kNN rule, benchmark rules and
    normalisation (its reflectance statistics in `data`'s reflectance scale)."""
    check_folder_profiles(network, data)
    scale = data.reflectance_max / network.reflectance_max
    means, stds = list(network.projection.means), list(network.projection.stds)
    means[4], stds[4] = means[4] * scale, stds[4] * scale
    projection = replace(data.projection, means=tuple(means), stds=tuple(stds))
    return replace(
        data,
        description=f"a network of the {network.name} profile on the {data.name} sensor",
        projection=projection,
        labels=replace(network.labels, splits=data.labels.splits),
        knn=network.knn,
        benchmark=network.benchmark,
    )


def output_map(network: DatasetProfile, label_map: LabelMap) -> LabelMap:
    """`label_map` once it is seen to list the raw id of every class the network can write
    (a point without a pixel included); a LabelMapError naming the first one it lacks."""
    ids = np.unique(np.asarray(network.labels.class_raw_ids, dtype=np.int64))
    missing = label_map.missing(ids)
    if missing.size:
        raw = int(missing[0])
        name = network.labels.class_names[network.labels.class_raw_ids.index(raw)]
        raise LabelMapError(
            f"{label_map.path}: raw id {raw} ({name}, a class of the {network.name} profile the "
            "network can predict) is not in the label map"
        )
    return label_map
