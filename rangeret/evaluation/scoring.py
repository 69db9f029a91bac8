"""How a benchmark turns a confusion matrix into IoU: one `Scoring` object per official evaluator.

- `SERVER_SCORING` (`semantickitti`): the SemanticKITTI evaluator's rules. The columns of ignored
  ground-truth classes are zeroed; IoU_c = TP / (TP + FP + FN + 1e-15); mIoU averages every
  evaluated class, so a class absent from both prediction and ground truth counts as 0.
- `DEVKIT_SCORING` (`nuscenes`): nuScenes-lidarseg's devkit's. The ignored class's row and column
  are both zeroed; IoU_c = TP / union with the union as float32 (as the devkit divides), undefined
  (NaN) for a class absent from both sides; mIoU is the mean over the defined classes, and the
  report adds the frequency-weighted IoU.

A profile names its scoring in its `benchmark.scoring` field; `scoring_named` finds the object.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

EPS = 1e-15


@dataclass(frozen=True)
class Scoring:
    """One evaluator's rules: what counts, how IoU divides, and how mIoU averages."""

    #: The name a profile's `benchmark.scoring` and a report's `scoring` key use.
    name: str
    #: The ignored classes' prediction rows are zeroed too (not only their ground-truth columns).
    zero_ignored_rows: bool = False
    #: IoU is undefined (NaN) for a class absent from both sides, and mIoU leaves it out.
    undefined_when_absent: bool = False
    #: The report carries the frequency-weighted IoU and names the scoring.
    reports_freq_weighted: bool = False

    def scored(self, matrix: np.ndarray, ignore: Sequence[int]) -> np.ndarray:
        """The counts that are scored: a copy of C[pred, gt] with the ignored classes zeroed."""
        conf = np.array(matrix, dtype=np.int64, copy=True)
        conf[:, list(ignore)] = 0
        if self.zero_ignored_rows:
            conf[list(ignore), :] = 0
        return conf

    def iou(self, tp: np.ndarray, fp: np.ndarray, fn: np.ndarray) -> np.ndarray:
        """IoU of every class from its true positives, false positives and false negatives."""
        if self.undefined_when_absent:
            with np.errstate(divide="ignore", invalid="ignore"):
                return tp / (tp + fp + fn).astype(np.float32)
        return tp / (tp + fp + fn + EPS)

    def mean(self, iou: np.ndarray, include: Sequence[int]) -> float:
        """mIoU over the evaluated classes `include` (NaN when no class is defined)."""
        if self.undefined_when_absent:
            if np.isnan(iou).all():
                return float("nan")
            return float(np.nanmean(iou))
        return float(iou[list(include)].mean())


SERVER_SCORING = Scoring("semantickitti")
DEVKIT_SCORING = Scoring(
    "nuscenes", zero_ignored_rows=True, undefined_when_absent=True, reports_freq_weighted=True
)
#: Every scoring by name, SemanticKITTI's (the default) first.
SCORINGS: dict[str, Scoring] = {s.name: s for s in (SERVER_SCORING, DEVKIT_SCORING)}


def scoring_named(name: str | Scoring) -> Scoring:
    """The scoring called `name` (a `Scoring` is returned as it is); ValueError naming the known
    ones otherwise."""
    if isinstance(name, Scoring):
        return name
    found = SCORINGS.get(name)
    if found is None:
        raise ValueError(f"scoring must be one of {', '.join(SCORINGS)}, got {name!r}")
    return found
