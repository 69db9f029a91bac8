"""From the scenes' SemanticKITTI labels to another profile's raw ids.

The scenes label their points with raw SemanticKITTI ids. A raw id that the profile's label
configuration knows by the same name, in a class of the same name, is kept (so SemanticKITTI and
profiles derived from it keep every id, moving classes and lane markings included). Every other
id goes by its SemanticKITTI class: a built-in profile's table below names the class standing for
it, any other profile takes the class of equal name; the id written is that class's raw id, and a
class without a counterpart becomes the profile's unlabeled class.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from rangeret.dataset.labels import SEMANTIC_MASK, semantickitti

if TYPE_CHECKING:
    from rangeret.dataset.profiles import DatasetProfile

#: SemanticKITTI class -> the class that stands for it in each built-in profile other than
#: SemanticKITTI's; classes left out (riders on PandaSet) have no counterpart. nuScenes counts a
#: rider with the vehicle ridden.
CLASS_TABLES: dict[str, dict[str, str]] = {
    "semantic-poss": {
        "car": "car",
        "truck": "car",
        "other-vehicle": "car",
        "bicycle": "bike",
        "motorcycle": "bike",
        "person": "person",
        "bicyclist": "rider",
        "motorcyclist": "rider",
        "road": "ground",
        "parking": "ground",
        "sidewalk": "ground",
        "other-ground": "ground",
        "terrain": "ground",
        "building": "building",
        "fence": "fence",
        "vegetation": "plants",
        "trunk": "trunk",
        "pole": "pole",
        "traffic-sign": "traffic-sign",
    },
    "pandaset": {
        "car": "car",
        "bicycle": "bicycle",
        "motorcycle": "motorcycle",
        "truck": "truck",
        "other-vehicle": "other-vehicle",
        "person": "person",
        "road": "road",
        "parking": "road",
        "sidewalk": "sidewalk",
        "other-ground": "ground",
        "terrain": "ground",
        "building": "building",
        "fence": "background",
        "vegetation": "vegetation",
        "trunk": "vegetation",
        "pole": "background",
        "traffic-sign": "traffic-sign",
    },
    "nuscenes": {
        "car": "car",
        "bicycle": "bicycle",
        "motorcycle": "motorcycle",
        "truck": "truck",
        "other-vehicle": "bus",
        "person": "pedestrian",
        "bicyclist": "bicycle",
        "motorcyclist": "motorcycle",
        "road": "driveable_surface",
        "parking": "driveable_surface",
        "sidewalk": "sidewalk",
        "other-ground": "other_flat",
        "terrain": "terrain",
        "building": "manmade",
        "fence": "manmade",
        "vegetation": "vegetation",
        "trunk": "vegetation",
        "pole": "manmade",
        "traffic-sign": "manmade",
    },
}


def class_table(profile: DatasetProfile) -> dict[str, str]:
    """SemanticKITTI class -> the profile's class standing for it: the built-in table of the
    profile, else equal names; classes missing from the result have no counterpart."""
    names = set(profile.labels.class_names)
    table = CLASS_TABLES.get(profile.name)
    pairs = table.items() if table is not None else ((n, n) for n in semantickitti().class_names)
    return {src: dst for src, dst in pairs if dst in names}


def raw_label_map(profile: DatasetProfile) -> np.ndarray:
    """(65536,) uint32 table from a scene's raw SemanticKITTI id to the raw id the profile's
    label configuration gives the same thing (its unlabeled class's raw id when nothing does)."""
    kitti = semantickitti()
    labels = profile.labels
    class_raw = dict(zip(labels.class_names, labels.class_raw_ids, strict=True))
    table = class_table(profile)
    lut = np.full(SEMANTIC_MASK + 1, labels.class_raw_ids[labels.unlabeled_class], dtype=np.uint32)
    for raw, cls in kitti.raw_to_class.items():
        name = kitti.class_names[cls]
        own = labels.raw_to_class.get(raw)
        if (
            own is not None
            and labels.raw_names.get(raw) == kitti.raw_names.get(raw)
            and labels.class_names[own] == name
        ):
            lut[raw] = raw
        elif name in table:
            lut[raw] = class_raw[table[name]]
    return lut
