"""Counting label files into confusion matrices: one per sequence and distance band.

`RawLabelEvaluator` takes each scan's prediction and ground truth as read from their files (raw
ids, or for nuScenes the challenge classes as predictions), maps them to training classes and
counts every point in the matrix of its scan's sequence and its distance band
(`rangeret.dataset.distance`); the report's matrices by sequence, by band and overall are sums of
those, so the parts add up to the whole exactly, and evaluators of many workers merge by addition.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from rangeret.dataset.distance import NUM_BANDS
from rangeret.dataset.labels import LabelConfig
from rangeret.evaluation.metrics import ConfusionMatrix, EvaluationReport
from rangeret.evaluation.scoring import SERVER_SCORING, Scoring, scoring_named

if TYPE_CHECKING:
    from rangeret.dataset.profiles import DatasetProfile


class RawLabelEvaluator:
    """Accumulates raw-id label arrays (as read from `.label` files) into confusion matrices.

    Both arrays are masked to their low 16 bits and mapped through the learning map; ids the map
    does not know count as the unlabeled class (0 for SemanticKITTI, as in the official
    evaluator), and unknown predicted ids are counted so a report can say so. Each point is counted
    in the matrix of its scan's sequence and its distance band; every other matrix (by sequence,
    by band, overall) is a sum of those.
    """

    def __init__(
        self,
        *,
        config: LabelConfig,
        predictions: str = "raw",
        scoring: Scoring | str = SERVER_SCORING,
        classes_from: int = 0,
    ) -> None:
        self.config = config
        self.scoring = scoring_named(scoring)
        self.predictions = predictions
        self.classes_from = classes_from
        n = self.config.num_classes
        self._n = n
        # Unknown ids map to the extra class n, folded into the unlabeled class when read.
        lut = np.full(1 << 16, n, dtype=np.uint8)
        for raw, cls in self.config.raw_to_class.items():
            lut[raw] = cls
        self._lut = lut
        # Predictions hold raw ids (the same map) or the classes themselves.
        if predictions == "class":
            self._pred_lut = np.full(1 << 16, n, dtype=np.uint8)
            self._pred_lut[:n] = np.arange(n, dtype=np.uint8)
        else:
            self._pred_lut = lut
        #: Counts per sequence: (NUM_BANDS, (n + 1) ** 2), cell band, pred * (n + 1) + gt.
        self._counts: dict[str, np.ndarray] = {}
        self.num_scans = 0
        self.num_points = 0

    @classmethod
    def for_profile(cls, profile: DatasetProfile) -> RawLabelEvaluator:
        """An evaluator with a profile's labels, and its benchmark's predictions and scoring."""
        return cls(
            config=profile.labels,
            predictions=profile.benchmark.predictions,
            scoring=profile.benchmark.scoring,
            classes_from=profile.benchmark.classes_from,
        )

    def refusal(self, pred: np.ndarray) -> str | None:
        """Why a prediction file's values are not what the benchmark takes, or None: where
        predictions are classes, each must be one of classes_from..C-1 (nuScenes refuses 0)."""
        if self.predictions != "class" or not pred.size:
            return None
        bad = np.flatnonzero((pred < self.classes_from) | (pred >= self._n))
        if not bad.size:
            return None
        return (
            f"holds {bad.size} value(s) outside the classes {self.classes_from}..{self._n - 1} "
            f"the benchmark takes, the first {int(pred[bad[0]])} at point {int(bad[0])}"
        )

    def prediction_classes(self, pred: np.ndarray) -> np.ndarray:
        """The training classes (uint8) of a prediction file's values; unknown values give C."""
        return self._pred_lut.take(_low16(pred))

    def add(
        self, pred_raw: np.ndarray, gt_raw: np.ndarray, sequence: str, bands: np.ndarray
    ) -> None:
        """Count one scan's raw predicted and ground-truth labels (same length) in its sequence,
        each point in its distance band (`rangeret.dataset.distance.distance_bands`)."""
        if pred_raw.shape != gt_raw.shape:
            raise ValueError(f"{pred_raw.size} predictions for {gt_raw.size} ground-truth labels")
        bands = np.asarray(bands).reshape(-1)
        if bands.size != pred_raw.size:
            raise ValueError(f"{bands.size} distance bands for {pred_raw.size} labels")
        if bands.size and (bands.min() < 0 or bands.max() >= NUM_BANDS):
            raise ValueError(f"distance bands must lie in 0..{NUM_BANDS - 1}")
        m = self._n + 1
        cells = NUM_BANDS * m * m
        # The lookup gives uint8 classes; all three indices combine in uint16 where they fit.
        wide = np.uint16 if cells <= 1 << 16 else np.intp
        p = self._pred_lut.take(_low16(pred_raw)).astype(wide)
        g = self._lut.take(_low16(gt_raw))
        index = bands.astype(wide) * wide(m * m) + p * wide(m) + g
        counts = np.bincount(index.reshape(-1), minlength=cells).reshape(NUM_BANDS, m * m)
        if sequence in self._counts:
            self._counts[sequence] += counts
        else:
            self._counts[sequence] = counts.astype(np.int64)
        self.num_scans += 1
        self.num_points += int(pred_raw.size)

    def merge(self, other: RawLabelEvaluator) -> None:
        """Add the counts of another evaluator over the same label configuration."""
        for sequence, counts in other._counts.items():
            if sequence in self._counts:
                self._counts[sequence] += counts
            else:
                self._counts[sequence] = counts.copy()
        self.num_scans += other.num_scans
        self.num_points += other.num_points

    def _band_totals(self) -> np.ndarray:
        """(NUM_BANDS, (n + 1) ** 2) counts summed over the sequences."""
        m = self._n + 1
        return sum(self._counts.values(), np.zeros((NUM_BANDS, m * m), dtype=np.int64))

    @property
    def unknown_prediction_ids(self) -> int:
        """How many predicted labels held a raw id the label configuration does not know."""
        n = self._n
        return int(self._band_totals().sum(axis=0).reshape(n + 1, n + 1)[n].sum())

    def _fold(self, counts: np.ndarray) -> ConfusionMatrix:
        """The confusion matrix of (n + 1) ** 2 counts, unknown ids counted as unlabeled."""
        n, u = self._n, self.config.unlabeled_class
        full = counts.reshape(n + 1, n + 1).copy()
        full[u] += full[n]
        full[:, u] += full[:, n]
        cm = ConfusionMatrix.for_config(config=self.config, scoring=self.scoring)
        cm.merge(full[:n, :n])
        return cm

    def confusion(self) -> ConfusionMatrix:
        """The confusion matrix, unknown ids counted as the unlabeled class."""
        return self._fold(self._band_totals().sum(axis=0))

    def by_sequence(self) -> dict[str, ConfusionMatrix]:
        """The confusion matrix of each sequence counted, in sequence order."""
        return {seq: self._fold(self._counts[seq].sum(axis=0)) for seq in sorted(self._counts)}

    def by_distance(self) -> list[ConfusionMatrix]:
        """The confusion matrix of each distance band, nearest first."""
        return [self._fold(counts) for counts in self._band_totals()]

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
            by_sequence=self.by_sequence(),
            by_distance=self.by_distance(),
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
