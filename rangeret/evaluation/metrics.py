"""Confusion matrices and the SemanticKITTI benchmark's IoU, mIoU and accuracy.

The counts are C[pred, gt] over the training classes; TP = diagonal, FP = row sum - TP,
FN = column sum - TP, accuracy = sum TP / (TP + FP over evaluated classes). Which counts are
scored and how IoU and mIoU divide are the benchmark's `Scoring` (`rangeret.evaluation.scoring`):
the SemanticKITTI evaluator's rules by default, nuScenes-lidarseg's devkit's for its profile.
Matrices are plain counts, so partial results
from many workers merge by addition. The evaluator (`rangeret.evaluation.counting`)
keeps one matrix per sequence and distance band (`rangeret.dataset.distance`); the report's matrices by
sequence, by band and overall are sums of those, so the parts add up to the whole exactly.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rangeret.dataset.distance import band_limits, band_name
from rangeret.dataset.labels import LabelConfig
from rangeret.evaluation.calibration import Calibration
from rangeret.evaluation.scoring import EPS, SERVER_SCORING, Scoring, scoring_named


def confusion_counts(pred: np.ndarray, gt: np.ndarray, num_classes: int) -> np.ndarray:
    """(C, C) int64 counts of (pred, gt) pairs of training classes, built with one bincount."""
    pred = np.asarray(pred).reshape(-1)
    gt = np.asarray(gt).reshape(-1)
    if pred.shape != gt.shape:
        raise ValueError(f"{pred.size} predictions for {gt.size} ground-truth labels")
    cells = num_classes * num_classes
    # With gt in range, a negative prediction gives a negative index (bincount refuses it) and a
    # prediction >= C an index past the last cell, so only gt needs an explicit range check.
    if gt.size and (gt.max() >= num_classes or (gt.dtype.kind == "i" and gt.min() < 0)):
        raise ValueError(f"ground-truth class ids must lie in 0..{num_classes - 1}")
    # uint8 classes (what the label lookup tables give) combine in uint16 without a wide copy.
    narrow = pred.dtype == gt.dtype == np.uint8 and cells <= 1 << 16
    wide = np.uint16 if narrow else np.intp
    try:
        counts = np.bincount(pred.astype(wide) * wide(num_classes) + gt, minlength=cells)
    except ValueError:
        counts = np.empty(0)
    if counts.size != cells:
        raise ValueError(f"predicted class ids must lie in 0..{num_classes - 1}")
    return counts.reshape(num_classes, num_classes).astype(np.int64, copy=False)


@dataclass
class ConfusionMatrix:
    """An accumulating confusion matrix C[pred, gt] with the official IoU semantics."""

    num_classes: int = 20
    ignore: tuple[int, ...] = (0,)
    matrix: np.ndarray = field(default=None)  # type: ignore[assignment]
    #: The benchmark's rules (a `Scoring`, or its name).
    scoring: Scoring = SERVER_SCORING

    def __post_init__(self) -> None:
        if self.matrix is None:
            self.matrix = np.zeros((self.num_classes, self.num_classes), dtype=np.int64)
        self.matrix = np.asarray(self.matrix, dtype=np.int64)
        if self.matrix.shape != (self.num_classes, self.num_classes):
            raise ValueError(
                f"confusion matrix must be {self.num_classes}x{self.num_classes}, "
                f"got {self.matrix.shape}"
            )
        self.ignore = tuple(int(c) for c in self.ignore)
        self.scoring = scoring_named(self.scoring)

    @classmethod
    def for_config(
        cls, *, config: LabelConfig, scoring: Scoring | str = SERVER_SCORING
    ) -> ConfusionMatrix:
        """An empty matrix shaped for a label configuration."""
        return cls(
            config.num_classes,
            tuple(c for c in range(config.num_classes) if config.ignored[c]),
            scoring=scoring,
        )

    @property
    def include(self) -> list[int]:
        """The classes that count in mIoU and accuracy."""
        return [c for c in range(self.num_classes) if c not in self.ignore]

    def add(self, pred: np.ndarray, gt: np.ndarray) -> None:
        """Count pairs of predicted and ground-truth training classes."""
        self.matrix += confusion_counts(pred, gt, self.num_classes)

    def merge(self, other: ConfusionMatrix | np.ndarray) -> None:
        """Add another matrix's counts (how results from several workers are reduced)."""
        counts = other.matrix if isinstance(other, ConfusionMatrix) else np.asarray(other)
        if counts.shape != self.matrix.shape:
            raise ValueError(f"cannot merge a {counts.shape} matrix into {self.matrix.shape}")
        self.matrix += counts.astype(np.int64, copy=False)

    def __add__(self, other: ConfusionMatrix) -> ConfusionMatrix:
        out = ConfusionMatrix(self.num_classes, self.ignore, self.matrix.copy(), self.scoring)
        out.merge(other)
        return out

    def scored(self) -> np.ndarray:
        """The counts that are scored, as the scoring zeroes the ignored classes."""
        return self.scoring.scored(self.matrix, self.ignore)

    def stats(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """TP, FP and FN per class of the scored counts."""
        conf = self.scored()
        tp = np.diag(conf)
        fp = conf.sum(axis=1) - tp
        fn = conf.sum(axis=0) - tp
        return tp, fp, fn

    def iou(self) -> np.ndarray:
        """IoU of every class (ignored ones included, as the official evaluators return them;
        NaN where the devkit's union is empty)."""
        return self.scoring.iou(*self.stats())

    def miou(self) -> float:
        """Mean IoU over the evaluated classes; absent classes count as 0, or scoring as the
        devkit are left out (NaN when no class is defined)."""
        return self.scoring.mean(self.iou(), self.include)

    def freq_weighted_iou(self) -> float:
        """Each class's IoU weighted by its share of the scored ground-truth points, as the
        devkit computes it (NaN without scored points)."""
        conf = self.scored()
        total = conf.sum()
        if not total:
            return float("nan")
        return float(np.nansum(conf.sum(axis=0) * self.iou()) / total)

    def accuracy(self) -> float:
        """Point accuracy: all TP over TP + FP of the evaluated classes."""
        tp, fp, _ = self.stats()
        inc = self.include
        return float(tp.sum() / (tp[inc].sum() + fp[inc].sum() + EPS))

    def evaluated_points(self) -> int:
        """Points whose ground truth is an evaluated class: those the scores are computed on."""
        return int(self.matrix[:, self.include].sum())


@dataclass
class EvaluationReport:
    """The result of an evaluation: the numbers of the benchmark and what they were computed on."""

    confusion: ConfusionMatrix
    class_names: tuple[str, ...]
    num_scans: int = 0
    num_points: int = 0
    sequences: list[str] = field(default_factory=list)
    unknown_prediction_ids: int = 0
    checkpoint_sha256: str | None = None
    notes: list[str] = field(default_factory=list)
    profile: str | None = None
    precision: str | None = None
    #: The inference backend the predictions came from (torch or onnxruntime), where known.
    backend: str | None = None
    by_sequence: dict[str, ConfusionMatrix] = field(default_factory=dict)
    by_distance: list[ConfusionMatrix] = field(default_factory=list)
    #: The calibration of the predictions' confidences, where every scan had them.
    calibration: Calibration | None = None

    @property
    def miou(self) -> float:
        return self.confusion.miou()

    @property
    def accuracy(self) -> float:
        return self.confusion.accuracy()

    def iou_by_name(self, confusion: ConfusionMatrix | None = None) -> dict[str, float | None]:
        """IoU (0..1) of each evaluated class, by class name (of `confusion`, default overall);
        None where it is undefined (scoring as the devkit, a class absent from both sides)."""
        confusion = confusion or self.confusion
        iou = confusion.iou()
        return {self.class_names[c]: _number(iou[c]) for c in confusion.include}

    def part_dict(self, confusion: ConfusionMatrix) -> dict:
        """The scores of one part of the data (a sequence, a distance band) for the JSON report."""
        out = {
            "miou": _number(confusion.miou()),
            "accuracy": confusion.accuracy(),
            "iou": self.iou_by_name(confusion),
            "points": confusion.evaluated_points(),
            "confusion": confusion.matrix.tolist(),
        }
        if confusion.scoring.reports_freq_weighted:
            out["freq_weighted_iou"] = _number(confusion.freq_weighted_iou())
        return out

    def to_dict(self) -> dict:
        """The JSON report: miou, accuracy, iou by name, the raw confusion[pred][gt], context, and
        the same scores per sequence and per distance band."""
        out: dict = {
            "miou": _number(self.miou),
            "accuracy": self.accuracy,
            "iou": self.iou_by_name(),
            **(
                {
                    "freq_weighted_iou": _number(self.confusion.freq_weighted_iou()),
                    "scoring": self.confusion.scoring.name,
                }
                if self.confusion.scoring.reports_freq_weighted
                else {}
            ),
            "confusion": self.confusion.matrix.tolist(),
            "class_names": list(self.class_names),
            "num_scans": self.num_scans,
            "num_points": self.num_points,
            "sequences": list(self.sequences),
            "unknown_prediction_ids": self.unknown_prediction_ids,
        }
        if self.by_sequence:
            out["per_sequence"] = {seq: self.part_dict(cm) for seq, cm in self.by_sequence.items()}
        if self.by_distance:
            out["per_distance"] = [
                dict(zip(("min_m", "max_m"), band_limits(band), strict=True), **self.part_dict(cm))
                for band, cm in enumerate(self.by_distance)
            ]
        if self.calibration is not None:
            out["calibration"] = self.calibration.to_dict()
        if self.checkpoint_sha256:
            out["checkpoint_sha256"] = self.checkpoint_sha256
        if self.profile:
            out["profile"] = self.profile
        if self.precision:
            out["precision"] = self.precision
        if self.backend:
            out["backend"] = self.backend
        if self.notes:
            out["notes"] = list(self.notes)
        return out

    def write_json(self, path: Path | str) -> None:
        """Write the JSON report, creating its folder."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_dict(cls, data: dict, *, config: LabelConfig) -> EvaluationReport:
        """Rebuild a report from its JSON form (class names it lacks are `config`'s)."""
        ignore = tuple(c for c in range(config.num_classes) if config.ignored[c])
        scoring = scoring_named(data.get("scoring", SERVER_SCORING.name))

        def matrix(counts: list) -> ConfusionMatrix:
            counts = np.asarray(counts, dtype=np.int64)
            return ConfusionMatrix(counts.shape[0], ignore, counts, scoring)

        return cls(
            confusion=matrix(data["confusion"]),
            class_names=tuple(data.get("class_names", config.class_names)),
            num_scans=int(data.get("num_scans", 0)),
            num_points=int(data.get("num_points", 0)),
            sequences=list(data.get("sequences", [])),
            unknown_prediction_ids=int(data.get("unknown_prediction_ids", 0)),
            checkpoint_sha256=data.get("checkpoint_sha256"),
            notes=list(data.get("notes", [])),
            profile=data.get("profile"),
            precision=data.get("precision"),
            backend=data.get("backend"),
            by_sequence={
                seq: matrix(part["confusion"]) for seq, part in data.get("per_sequence", {}).items()
            },
            by_distance=[matrix(part["confusion"]) for part in data.get("per_distance", [])],
            calibration=Calibration.from_dict(data["calibration"])
            if "calibration" in data
            else None,
        )

    def points_line(self) -> str:
        """How many points were predicted and how many of them scored: those whose ground truth
        is an ignored class (unlabeled) are predicted but count in no score."""
        scored = self.confusion.evaluated_points()
        line = (
            f"{self.num_scans:,} scans, {self.num_points:,} points predicted, {scored:,} of them "
            "scored"
        )
        if self.num_points > scored:
            ignored = " or ".join(self.class_names[c] for c in self.confusion.ignore) or "ignored"
            line += (
                f" (the other {self.num_points - scored:,} have the ground truth {ignored}, "
                "which is not scored)"
            )
        return line

    def table(self) -> str:
        """A readable per-class table with IoU in percent, followed by mIoU and accuracy."""
        tp, fp, fn = self.confusion.stats()
        iou = self.confusion.iou()
        width = max(len(n) for n in self.class_names)
        lines = [f"{'class':<{width}}  {'IoU %':>6}  {'gt points':>11}  {'predicted':>11}"]
        for c in self.confusion.include:
            lines.append(
                f"{self.class_names[c]:<{width}}  {_percent(iou[c])}  {tp[c] + fn[c]:>11,}  "
                f"{tp[c] + fp[c]:>11,}"
            )
        lines.append("-" * len(lines[0]))
        lines.append(f"{'mIoU':<{width}}  {_percent(self.miou)}")
        if self.confusion.scoring.reports_freq_weighted:
            lines.append(f"{'fw IoU':<{width}}  {_percent(self.confusion.freq_weighted_iou())}")
        lines.append(f"{'accuracy':<{width}}  {100 * self.accuracy:6.2f}")
        lines.append(self.points_line())
        parts = [
            ("sequence", list(self.by_sequence.items())),
            ("distance", [(band_name(b), cm) for b, cm in enumerate(self.by_distance)]),
        ]
        for title, rows in parts:
            if rows:
                lines.append("")
                lines.extend(_parts_table(title, rows))
        if self.calibration is not None:
            lines.append("")
            lines.append(
                f"confidence calibration: ECE {100 * self.calibration.ece():.2f} % over "
                f"{self.calibration.points:,} points"
            )
        return "\n".join(lines)


def _number(value: float) -> float | None:
    """A score for the JSON report: None where it is undefined (NaN)."""
    value = float(value)
    return None if np.isnan(value) else value


def _percent(value: float) -> str:
    """A score in percent, six characters wide ("   n/a" where it is undefined)."""
    return "   n/a" if np.isnan(value) else f"{100 * value:6.2f}"


def _parts_table(title: str, rows: list[tuple[str, ConfusionMatrix]]) -> list[str]:
    """Lines of scored points, mIoU and accuracy (percent) per part, headed by `title`."""
    width = max(len(title), *(len(name) for name, _ in rows))
    lines = [f"{title:<{width}}  {'scored points':>13}  {'mIoU %':>6}  {'accuracy %':>10}"]
    for name, cm in rows:
        lines.append(
            f"{name:<{width}}  {cm.evaluated_points():>13,}  {_percent(cm.miou())}  "
            f"{100 * cm.accuracy():10.2f}"
        )
    return lines
