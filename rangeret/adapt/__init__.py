"""A labelled dataset resampled to another sensor, so a model can be trained for that sensor.

- `resample`: `adapt_scan`, one scan as the target sensor would keep it (pure numpy), and the
  checks of the profiles and the sensor offset;
- `rangeret.dataset.label_map`: the optional map from the source's raw ids to the target's;
- `tree`: `plan_adaptation`, `adapt_one`, `finish` and `summary`, the steps every driver of a
  whole dataset shares (the `rangeret adapt` command, a Ray job), whose options are
  `rangeret.options.add_adapt_options`.
"""

from rangeret.adapt.resample import AdaptError, AdaptStats, adapt_scan, unmeasured_beams
from rangeret.adapt.tree import (
    ADAPT_INFO,
    AdaptPlan,
    AdaptSettings,
    ScanJob,
    adapt_one,
    finish,
    plan_adaptation,
    read_adapt_info,
    summary,
)
from rangeret.dataset.label_map import LabelMap, LabelMapError, UnknownLabelError, load_label_map

__all__ = [
    "ADAPT_INFO",
    "AdaptError",
    "AdaptPlan",
    "AdaptSettings",
    "AdaptStats",
    "LabelMap",
    "LabelMapError",
    "ScanJob",
    "UnknownLabelError",
    "adapt_one",
    "adapt_scan",
    "finish",
    "load_label_map",
    "plan_adaptation",
    "read_adapt_info",
    "summary",
    "unmeasured_beams",
]
