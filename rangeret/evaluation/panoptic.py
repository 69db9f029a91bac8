"""Panoptic quality (PQ, SQ, RQ) with the semantic IoU the panoptic benchmarks report beside it,
counted scan by scan: one `PanopticCounts` accumulator, one `PanopticRules` object per official
evaluator.

The counting rules both official evaluators share (nuScenes' devkit took SemanticKITTI's code):

- A segment is a (class, instance id) pair. Every class is segmented alike: stuff classes are not
  merged into one segment per scan, so a stuff class is one segment only where its points share
  one instance id. What the official scripts pass as the instance id is the whole label:
  SemanticKITTI's 32-bit `.label` value (instance << 16 | raw semantic id), nuScenes' panoptic
  value (1000 * class + instance). So two raw classes that map to one training class (road and
  lane-marking, car and moving-car) are separate segments, and so are predicted stuff points
  with different instance ids.
- Points whose ground-truth class is ignored are dropped before segmenting; a predicted segment
  of an ignored class counts nowhere.
- A predicted and a ground-truth segment of one class match when their IoU (points) is > 0.5:
  a true positive adding that IoU. Unmatched segments count as false positives (predicted) or
  false negatives (ground truth) only when they hold at least `min_points` points; matched ones
  count whatever their size, and stuff classes fall under the same limit.
- SQ = sum IoU / max(TP, eps), RQ = TP / max(TP + FP / 2 + FN / 2, eps), PQ = SQ * RQ, with
  eps = 1e-15, so an absent class scores 0, not NaN.
- The semantic IoU comes from a confusion matrix of every point (ignored ground truth included)
  with the ignored classes' ground-truth columns zeroed: IoU = TP / max(TP + FP + FN, eps), 0 for
  an absent class, and mIoU averages every non-ignored class. For nuScenes this is not the
  lidarseg devkit's IoU (`rangeret.evaluation.scoring.DEVKIT_SCORING`, NaN for an absent class).
- Things and stuff differ only in which means and PQ† (PQ for things, IoU for stuff) take them.

What differs is the rule objects':

- `KITTI_PANOPTIC` (`semantickitti`, `evaluate_panoptic.py`): at least 50 points; the report
  holds the eleven scores.txt keys (`pq_mean`, `pq_dagger`, ..., `sq_things`), the PQ, SQ and RQ
  means over things and over stuff among them, and under `classes` each evaluated class's `pq`,
  `sq`, `rq`, `iou`.
- `DEVKIT_PANOPTIC` (`nuscenes`, nuscenes-devkit 1.2.0's `NuScenesPanopticEval`, task
  segmentation): at least 15 points; the report is the devkit's `segmentation` dict, `all` with
  `PQ`, `SQ`, `RQ`, `mIoU`, `PQ_dagger`, and every class, the ignored one included, with `PQ`,
  `SQ`, `RQ`, `IoU`. Its means average the evaluated classes in index order (SemanticKITTI's
  its things list, then its stuff list), which differs only in float rounding.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: The guard both evaluators divide by (SQ, RQ and IoU of an absent class are 0).
EPS = 1e-15
#: The factor both evaluators combine (pred + 1) + offset * (gt + 1) instance ids with, in int64.
OFFSET = 2**32
#: A predicted and a ground-truth segment match when their IoU is strictly above this.
MATCH_IOU = 0.5


@dataclass(frozen=True)
class PanopticScores:
    """Per-class PQ, SQ, RQ and IoU with the class split a report averages over."""

    class_names: tuple[str, ...]
    pq: np.ndarray
    sq: np.ndarray
    rq: np.ndarray
    iou: np.ndarray
    #: The non-ignored classes, in index order.
    evaluated: tuple[int, ...]
    things: tuple[int, ...]
    #: The non-ignored classes that are not things, in index order.
    stuff: tuple[int, ...]

    def mean(self, values: np.ndarray, classes: Sequence[int]) -> float:
        """The mean of `values` over `classes` in their order; NaN when there is none."""
        if not len(classes):
            return float("nan")
        return float(np.mean(values[list(classes)]))

    def dagger(self) -> float:
        """PQ†: the mean of the things' PQ and the stuff's IoU."""
        parts = np.concatenate([self.pq[list(self.things)], self.iou[list(self.stuff)]])
        return float(np.mean(parts)) if parts.size else float("nan")

    def of_class(self, c: int, keys: tuple[str, str, str, str]) -> dict[str, float]:
        """Class `c`'s PQ, SQ, RQ and IoU under the report's `keys` (in that order)."""
        values = (self.pq[c], self.sq[c], self.rq[c], self.iou[c])
        return {k: float(v) for k, v in zip(keys, values, strict=True)}


def kitti_summary(s: PanopticScores) -> dict[str, Any]:
    """`evaluate_panoptic.py`'s scores: its means over its things then stuff lists (mIoU over the
    evaluated classes), then under `classes` each evaluated class by name."""
    named = [*s.things, *s.stuff]
    out: dict[str, Any] = {
        "pq_mean": s.mean(s.pq, named),
        "pq_dagger": s.dagger(),
        "sq_mean": s.mean(s.sq, named),
        "rq_mean": s.mean(s.rq, named),
        "iou_mean": s.mean(s.iou, s.evaluated),
        "pq_stuff": s.mean(s.pq, s.stuff),
        "rq_stuff": s.mean(s.rq, s.stuff),
        "sq_stuff": s.mean(s.sq, s.stuff),
        "pq_things": s.mean(s.pq, s.things),
        "rq_things": s.mean(s.rq, s.things),
        "sq_things": s.mean(s.sq, s.things),
    }
    out["classes"] = {
        s.class_names[c]: s.of_class(c, ("pq", "sq", "rq", "iou")) for c in s.evaluated
    }
    return out


def devkit_summary(s: PanopticScores) -> dict[str, Any]:
    """`NuScenesPanopticEval`'s segmentation results: `all` (means over the evaluated classes,
    PQ†), then every class by name, the ignored one included."""
    out: dict[str, Any] = {
        "all": {
            "PQ": s.mean(s.pq, s.evaluated),
            "SQ": s.mean(s.sq, s.evaluated),
            "RQ": s.mean(s.rq, s.evaluated),
            "mIoU": s.mean(s.iou, s.evaluated),
            "PQ_dagger": s.dagger(),
        }
    }
    for c, name in enumerate(s.class_names):
        out[name] = s.of_class(c, ("PQ", "SQ", "RQ", "IoU"))
    return out


@dataclass(frozen=True)
class PanopticRules:
    """One official panoptic evaluator: its minimum segment size, its thing classes and its
    report; the counting itself (module docstring) is common to both."""

    #: The name the matching semantic `Scoring` uses too.
    name: str
    #: Unmatched segments smaller than this count as neither false positive nor false negative.
    min_points: int
    #: The classes the evaluator counts as things (all others that are not ignored are stuff).
    thing_names: tuple[str, ...]
    #: The report of a `PanopticScores`, keyed as the official output.
    summarise: Callable[[PanopticScores], dict[str, Any]] = field(repr=False)
    offset: int = OFFSET
    eps: float = EPS

    def thing_classes(self, class_names: Sequence[str]) -> list[int]:
        """The indices of this evaluator's things among `class_names`; ValueError if one is absent."""
        missing = [n for n in self.thing_names if n not in class_names]
        if missing:
            raise ValueError(f"{self.name} things missing from the classes: {', '.join(missing)}")
        return sorted(list(class_names).index(n) for n in self.thing_names)

    @property
    def max_pred_instance(self) -> int:
        """The largest predicted instance id the official offset arithmetic keeps apart."""
        return self.offset - 2

    @property
    def max_gt_instance(self) -> int:
        """The largest ground-truth instance id whose offset product fits the official int64."""
        return 2**63 // self.offset - 2


KITTI_PANOPTIC = PanopticRules(
    "semantickitti",
    min_points=50,
    thing_names=(
        "car",
        "truck",
        "bicycle",
        "motorcycle",
        "other-vehicle",
        "person",
        "bicyclist",
        "motorcyclist",
    ),
    summarise=kitti_summary,
)
DEVKIT_PANOPTIC = PanopticRules(
    "nuscenes",
    min_points=15,
    thing_names=(
        "barrier",
        "bicycle",
        "bus",
        "car",
        "construction_vehicle",
        "motorcycle",
        "pedestrian",
        "traffic_cone",
        "trailer",
        "truck",
    ),
    summarise=devkit_summary,
)
#: Every panoptic rules object by name, SemanticKITTI's first.
PANOPTIC_RULES: dict[str, PanopticRules] = {r.name: r for r in (KITTI_PANOPTIC, DEVKIT_PANOPTIC)}


class PanopticCounts:
    """Accumulates panoptic and semantic counts scan by scan under one evaluator's rules.

    The counts are integers (TP, FP, FN per class, the confusion matrix) and a float sum of the
    matched IoUs, so counters of sequences, distance bands or workers `merge` into the whole.
    """

    def __init__(
        self,
        num_classes: int,
        ignore: Sequence[int],
        things: Sequence[int],
        rules: PanopticRules,
        min_points: int | None = None,
    ) -> None:
        if num_classes < 1:
            raise ValueError(f"num_classes must be positive, got {num_classes}")
        self.num_classes = int(num_classes)
        self.ignore = tuple(sorted({int(c) for c in ignore}))
        self.things = tuple(sorted({int(c) for c in things}))
        for what, classes in (("ignore", self.ignore), ("things", self.things)):
            if any(c < 0 or c >= num_classes for c in classes):
                raise ValueError(f"{what} classes must lie in 0..{num_classes - 1}")
        if set(self.ignore) & set(self.things):
            raise ValueError("a thing class cannot be ignored")
        self.rules = rules
        self.min_points = rules.min_points if min_points is None else int(min_points)
        self._ignored = np.zeros(num_classes, dtype=bool)
        self._ignored[list(self.ignore)] = True
        self.evaluated = tuple(int(c) for c in np.flatnonzero(~self._ignored))
        self.stuff = tuple(c for c in self.evaluated if c not in self.things)
        #: C[pred, gt] over every point, ignored ground truth included.
        self.confusion = np.zeros((num_classes, num_classes), dtype=np.int64)
        self.tp = np.zeros(num_classes, dtype=np.int64)
        self.fp = np.zeros(num_classes, dtype=np.int64)
        self.fn = np.zeros(num_classes, dtype=np.int64)
        #: The sum of the matched segments' IoU per class.
        self.iou_sum = np.zeros(num_classes, dtype=np.float64)
        self.num_scans = 0

    @classmethod
    def for_classes(
        cls,
        class_names: Sequence[str],
        ignore: Sequence[int],
        rules: PanopticRules,
        min_points: int | None = None,
    ) -> PanopticCounts:
        """A counter for `class_names` with the evaluator's own thing classes."""
        return cls(len(class_names), ignore, rules.thing_classes(class_names), rules, min_points)

    def _classes(self, values: Any, what: str) -> np.ndarray:
        """`values` as a flat int64 array of classes; ValueError outside 0..C-1."""
        arr = _integers(values, what)
        if arr.size and (arr.min() < 0 or arr.max() >= self.num_classes):
            raise ValueError(f"{what} must lie in 0..{self.num_classes - 1}")
        return arr.astype(np.int64, copy=False)

    def add(
        self,
        pred_class: np.ndarray,
        pred_instance: np.ndarray,
        gt_class: np.ndarray,
        gt_instance: np.ndarray,
    ) -> None:
        """Count one scan: (N,) training classes and instance ids of its predicted and
        ground-truth points. Instance ids are integers from 0 up to the rules'
        `max_pred_instance` / `max_gt_instance`, the range the official evaluators count exactly."""
        pc = self._classes(pred_class, "predicted classes")
        gc = self._classes(gt_class, "ground-truth classes")
        pi = _integers(pred_instance, "predicted instances")
        gi = _integers(gt_instance, "ground-truth instances")
        if not pc.size == pi.size == gc.size == gi.size:
            raise ValueError(
                f"{pc.size} predicted classes, {pi.size} predicted instances, {gc.size} "
                f"ground-truth classes and {gi.size} ground-truth instances differ"
            )
        for ids, top, what in (
            (pi, self.rules.max_pred_instance, "predicted instances"),
            (gi, self.rules.max_gt_instance, "ground-truth instances"),
        ):
            if ids.size and (ids.min() < 0 or ids.max() > top):
                raise ValueError(f"{what} must lie in 0..{top}")
        n = self.num_classes
        self.confusion += np.bincount(pc * n + gc, minlength=n * n).reshape(n, n)
        self.num_scans += 1

        keep = ~self._ignored[gc]
        pc, pi, gc, gi = pc[keep], pi[keep], gc[keep], gi[keep]
        counted = ~self._ignored[pc]
        counted_seg, pred_area, pred_cls = _segments(pc[counted], pi[counted])
        pred_seg = np.full(pc.size, -1, dtype=np.int64)
        pred_seg[counted] = counted_seg
        gt_seg, gt_area, gt_cls = _segments(gc, gi)

        # Points of one class on both sides; pc == gc leaves out predictions of ignored classes.
        both = pc == gc
        pairs, inter = np.unique(pred_seg[both] * gt_area.size + gt_seg[both], return_counts=True)
        p, g = pairs // max(gt_area.size, 1), pairs % max(gt_area.size, 1)
        iou = inter / (pred_area[p] + gt_area[g] - inter).astype(np.float64)
        hit = iou > MATCH_IOU
        self.tp += np.bincount(gt_cls[g[hit]], minlength=n)
        self.iou_sum += np.bincount(gt_cls[g[hit]], weights=iou[hit], minlength=n)

        matched_pred = np.zeros(pred_area.size, dtype=bool)
        matched_pred[p[hit]] = True
        matched_gt = np.zeros(gt_area.size, dtype=bool)
        matched_gt[g[hit]] = True
        lone_pred = ~matched_pred & (pred_area >= self.min_points)
        lone_gt = ~matched_gt & (gt_area >= self.min_points)
        self.fp += np.bincount(pred_cls[lone_pred], minlength=n)
        self.fn += np.bincount(gt_cls[lone_gt], minlength=n)

    def merge(self, other: PanopticCounts) -> None:
        """Add the counts of another counter with the same classes, rules and minimum size."""
        same = (
            other.num_classes == self.num_classes
            and other.ignore == self.ignore
            and other.things == self.things
            and other.rules == self.rules
            and other.min_points == self.min_points
        )
        if not same:
            raise ValueError("can only merge panoptic counts of the same classes and rules")
        self.confusion += other.confusion
        self.tp += other.tp
        self.fp += other.fp
        self.fn += other.fn
        self.iou_sum += other.iou_sum
        self.num_scans += other.num_scans

    def semantic_iou(self) -> np.ndarray:
        """(C,) IoU of every class from the confusion matrix, the ignored columns zeroed."""
        conf = self.confusion.astype(np.float64)
        conf[:, list(self.ignore)] = 0
        tp = conf.diagonal()
        union = conf.sum(axis=1) + conf.sum(axis=0) - tp
        return tp / np.maximum(union, self.rules.eps)

    def per_class(self) -> dict[str, np.ndarray]:
        """(C,) arrays `pq`, `sq`, `rq` and `iou` of every class, the ignored ones included."""
        eps = self.rules.eps
        tp = self.tp.astype(np.float64)
        sq = self.iou_sum / np.maximum(tp, eps)
        rq = tp / np.maximum(tp + 0.5 * self.fp + 0.5 * self.fn, eps)
        return {"pq": sq * rq, "sq": sq, "rq": rq, "iou": self.semantic_iou()}

    def scores(self, class_names: Sequence[str]) -> PanopticScores:
        """The per-class scores with the class names and the split a report averages over."""
        if len(class_names) != self.num_classes:
            raise ValueError(f"{len(class_names)} class names for {self.num_classes} classes")
        return PanopticScores(
            class_names=tuple(class_names),
            evaluated=self.evaluated,
            things=self.things,
            stuff=self.stuff,
            **self.per_class(),
        )

    def summary(self, class_names: Sequence[str]) -> dict[str, Any]:
        """The report under the official evaluator's keys (`PanopticRules.summarise`)."""
        return self.rules.summarise(self.scores(class_names))


def _integers(values: Any, what: str) -> np.ndarray:
    """`values` flattened; ValueError unless they are integers."""
    arr = np.asarray(values).reshape(-1)
    if not arr.size:
        return arr.astype(np.int64)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{what} must be integers, got {arr.dtype}")
    if arr.dtype == np.uint64 and arr.max() > np.iinfo(np.int64).max:
        raise ValueError(f"{what} must fit int64")
    return arr.astype(np.int64, copy=False)


def _segments(classes: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's segment (a distinct (class, id) pair), every segment's size and class."""
    _, rank = np.unique(ids, return_inverse=True)
    span = max(int(rank.max()) + 1 if rank.size else 1, 1)
    keys, seg, area = np.unique(
        classes * span + rank.reshape(-1), return_inverse=True, return_counts=True
    )
    return seg.reshape(-1), area, keys // span
