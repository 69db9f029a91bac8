"""Confusion matrices and the SemanticKITTI benchmark's IoU, mIoU and accuracy.

The semantics are the official evaluator's: C[pred, gt] over the training classes; the columns of
ignored ground-truth classes are zeroed; TP = diagonal, FP = row sum - TP, FN = column sum - TP;
IoU_c = TP / (TP + FP + FN + 1e-15); mIoU averages every evaluated class, so a class absent from
both prediction and ground truth counts as 0; accuracy = sum TP / (TP + FP over evaluated classes).
Matrices are plain counts, so partial results from many workers merge by addition.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rangeret.labels import LabelConfig, semantickitti

EPS = 1e-15


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

    @classmethod
    def for_config(cls, config: LabelConfig | None = None) -> ConfusionMatrix:
        """An empty matrix shaped for a label configuration."""
        config = config or semantickitti()
        return cls(
            config.num_classes, tuple(c for c in range(config.num_classes) if config.ignored[c])
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
        out = ConfusionMatrix(self.num_classes, self.ignore, self.matrix.copy())
        out.merge(other)
        return out

    def stats(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """TP, FP and FN per class after zeroing the ignored ground-truth columns."""
        conf = self.matrix.copy()
        conf[:, list(self.ignore)] = 0
        tp = np.diag(conf)
        fp = conf.sum(axis=1) - tp
        fn = conf.sum(axis=0) - tp
        return tp, fp, fn

    def iou(self) -> np.ndarray:
        """IoU of every class (ignored ones included, as the official evaluator returns them)."""
        tp, fp, fn = self.stats()
        return tp / (tp + fp + fn + EPS)

    def miou(self) -> float:
        """Mean IoU over the evaluated classes; absent classes count as 0."""
        return float(self.iou()[self.include].mean())

    def accuracy(self) -> float:
        """Point accuracy: all TP over TP + FP of the evaluated classes."""
        tp, fp, _ = self.stats()
        inc = self.include
        return float(tp.sum() / (tp[inc].sum() + fp[inc].sum() + EPS))


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

    @property
    def miou(self) -> float:
        return self.confusion.miou()

    @property
    def accuracy(self) -> float:
        return self.confusion.accuracy()

    def iou_by_name(self) -> dict[str, float]:
        """IoU (0..1) of each evaluated class, by class name."""
        iou = self.confusion.iou()
        return {self.class_names[c]: float(iou[c]) for c in self.confusion.include}

    def to_dict(self) -> dict:
        """The JSON report: miou, accuracy, iou by name, the raw confusion[pred][gt] and context."""
        out: dict = {
            "miou": self.miou,
            "accuracy": self.accuracy,
            "iou": self.iou_by_name(),
            "confusion": self.confusion.matrix.tolist(),
            "class_names": list(self.class_names),
            "num_scans": self.num_scans,
            "num_points": self.num_points,
            "sequences": list(self.sequences),
            "unknown_prediction_ids": self.unknown_prediction_ids,
        }
        if self.checkpoint_sha256:
            out["checkpoint_sha256"] = self.checkpoint_sha256
        if self.profile:
            out["profile"] = self.profile
        if self.precision:
            out["precision"] = self.precision
        if self.notes:
            out["notes"] = list(self.notes)
        return out

    def write_json(self, path: Path | str) -> None:
        """Write the JSON report, creating its folder."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_dict(cls, data: dict, config: LabelConfig | None = None) -> EvaluationReport:
        """Rebuild a report from its JSON form."""
        config = config or semantickitti()
        matrix = np.asarray(data["confusion"], dtype=np.int64)
        ignore = tuple(c for c in range(config.num_classes) if config.ignored[c])
        return cls(
            confusion=ConfusionMatrix(matrix.shape[0], ignore, matrix),
            class_names=tuple(data.get("class_names", config.class_names)),
            num_scans=int(data.get("num_scans", 0)),
            num_points=int(data.get("num_points", 0)),
            sequences=list(data.get("sequences", [])),
            unknown_prediction_ids=int(data.get("unknown_prediction_ids", 0)),
            checkpoint_sha256=data.get("checkpoint_sha256"),
            notes=list(data.get("notes", [])),
            profile=data.get("profile"),
            precision=data.get("precision"),
        )

    def table(self) -> str:
        """A readable per-class table with IoU in percent, followed by mIoU and accuracy."""
        tp, fp, fn = self.confusion.stats()
        iou = self.confusion.iou()
        width = max(len(n) for n in self.class_names)
        lines = [f"{'class':<{width}}  {'IoU %':>6}  {'gt points':>11}  {'predicted':>11}"]
        for c in self.confusion.include:
            lines.append(
                f"{self.class_names[c]:<{width}}  {100 * iou[c]:6.2f}  {tp[c] + fn[c]:>11,}  "
                f"{tp[c] + fp[c]:>11,}"
            )
        lines.append("-" * len(lines[0]))
        lines.append(f"{'mIoU':<{width}}  {100 * self.miou:6.2f}")
        lines.append(f"{'accuracy':<{width}}  {100 * self.accuracy:6.2f}")
        lines.append(f"{self.num_scans:,} scans, {self.num_points:,} points")
        return "\n".join(lines)


class RawLabelEvaluator:
    """Accumulates raw-id label arrays (as read from `.label` files) into a confusion matrix.

    Both arrays are masked to their low 16 bits and mapped through the learning map; ids the map
    does not know count as the unlabeled class (0 for SemanticKITTI, as in the official
    evaluator), and unknown predicted ids are counted so a report can say so.
    """

    def __init__(self, config: LabelConfig | None = None) -> None:
        self.config = config or semantickitti()
        n = self.config.num_classes
        self._n = n
        # Unknown ids map to the extra class n, folded into the unlabeled class when read.
        lut = np.full(1 << 16, n, dtype=np.uint8)
        for raw, cls in self.config.raw_to_class.items():
            lut[raw] = cls
        self._lut = lut
        self._counts = np.zeros((n + 1) * (n + 1), dtype=np.int64)
        self.num_scans = 0
        self.num_points = 0

    def add(self, pred_raw: np.ndarray, gt_raw: np.ndarray) -> None:
        """Count one scan's raw predicted and ground-truth labels (same length)."""
        if pred_raw.shape != gt_raw.shape:
            raise ValueError(f"{pred_raw.size} predictions for {gt_raw.size} ground-truth labels")
        p = self._lut.take(_low16(pred_raw))
        g = self._lut.take(_low16(gt_raw))
        self._counts += confusion_counts(p, g, self._n + 1).reshape(-1)
        self.num_scans += 1
        self.num_points += int(pred_raw.size)

    def merge(self, other: RawLabelEvaluator) -> None:
        """Add the counts of another evaluator over the same label configuration."""
        self._counts += other._counts
        self.num_scans += other.num_scans
        self.num_points += other.num_points

    @property
    def unknown_prediction_ids(self) -> int:
        """How many predicted labels held a raw id the label configuration does not know."""
        n = self._n
        return int(self._counts.reshape(n + 1, n + 1)[n].sum())

    def confusion(self) -> ConfusionMatrix:
        """The confusion matrix, unknown ids counted as the unlabeled class."""
        n, u = self._n, self.config.unlabeled_class
        full = self._counts.reshape(n + 1, n + 1).copy()
        full[u] += full[n]
        full[:, u] += full[:, n]
        cm = ConfusionMatrix.for_config(self.config)
        cm.merge(full[:n, :n])
        return cm

    def report(
        self, sequences: Sequence[str] = (), checkpoint_sha256: str | None = None
    ) -> EvaluationReport:
        """The evaluation report of everything added so far."""
        notes = []
        if self.unknown_prediction_ids:
            notes.append(
                f"{self.unknown_prediction_ids} predicted labels held raw ids the label "
                "configuration does not know; they were counted as unlabeled"
            )
        return EvaluationReport(
            confusion=self.confusion(),
            class_names=self.config.class_names,
            num_scans=self.num_scans,
            num_points=self.num_points,
            sequences=list(sequences),
            unknown_prediction_ids=self.unknown_prediction_ids,
            checkpoint_sha256=checkpoint_sha256,
            notes=notes,
        )


def _low16(raw: np.ndarray) -> np.ndarray:
    """The low 16 bits of uint32 labels as a uint16 view (little-endian) or a masked copy."""
    raw = np.asarray(raw)
    if (
        np.little_endian
        and raw.dtype == np.uint32
        and raw.dtype.isnative
        and raw.flags.c_contiguous
    ):
        return raw.view(np.uint16)[::2]
    return (raw.astype(np.int64) & 0xFFFF).astype(np.uint16)
