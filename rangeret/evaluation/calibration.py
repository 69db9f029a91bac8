"""Calibration of point confidences: how often a label given with confidence c is right.

Points are put in equal-width confidence bins; each bin keeps its point count, the sum of the
confidences and the number of correct labels, so scans add up by addition, like confusion
matrices. The expected calibration error (ECE) is the count-weighted mean gap between a bin's
accuracy and its mean confidence. Only points whose ground truth is not the ignored class count,
as in the confusion matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Equal-width confidence bins over [0, 1].
BINS = 10


@dataclass
class Calibration:
    """Per-bin point counts, confidence sums and correct labels, accumulated scan by scan."""

    bins: int = BINS
    count: np.ndarray = field(default=None)  # type: ignore[assignment]
    confidence: np.ndarray = field(default=None)  # type: ignore[assignment]
    correct: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.count is None:
            self.count = np.zeros(self.bins, dtype=np.int64)
            self.confidence = np.zeros(self.bins, dtype=np.float64)
            self.correct = np.zeros(self.bins, dtype=np.int64)

    def add(self, confidence: np.ndarray, correct: np.ndarray) -> None:
        """Count one scan's evaluated points: their confidences and whether each is right."""
        confidence = np.clip(np.asarray(confidence, dtype=np.float64), 0.0, 1.0)
        index = np.minimum((confidence * self.bins).astype(np.int64), self.bins - 1)
        self.count += np.bincount(index, minlength=self.bins)
        self.confidence += np.bincount(index, weights=confidence, minlength=self.bins)
        self.correct += np.bincount(index[np.asarray(correct, dtype=bool)], minlength=self.bins)

    def merge(self, other: Calibration) -> None:
        """Add another accumulation (of other scans) to this one."""
        self.count += other.count
        self.confidence += other.confidence
        self.correct += other.correct

    @property
    def points(self) -> int:
        """Points counted."""
        return int(self.count.sum())

    def ece(self) -> float:
        """The expected calibration error: sum over bins of (points share) x |accuracy - mean
        confidence|; 0 without points."""
        total = self.count.sum()
        if not total:
            return 0.0
        used = self.count > 0
        gap = np.abs(
            self.correct[used] / self.count[used] - self.confidence[used] / self.count[used]
        )
        return float((self.count[used] / total * gap).sum())

    def to_dict(self) -> dict:
        """The report's `calibration`: the ECE and, per bin, its range, points, mean confidence
        and accuracy (null for an empty bin)."""
        rows = []
        for b in range(self.bins):
            n = int(self.count[b])
            rows.append(
                {
                    "min": b / self.bins,
                    "max": (b + 1) / self.bins,
                    "points": n,
                    "confidence": float(self.confidence[b] / n) if n else None,
                    "accuracy": float(self.correct[b] / n) if n else None,
                }
            )
        return {"ece": self.ece(), "points": self.points, "bins": rows}

    @classmethod
    def from_dict(cls, data: dict) -> Calibration:
        """Rebuild the accumulation from a report's `calibration` (counts exact, sums to the
        precision the report keeps)."""
        rows = data["bins"]
        count = np.array([row["points"] for row in rows], dtype=np.int64)
        mean = np.array([row["confidence"] or 0.0 for row in rows], dtype=np.float64)
        accuracy = np.array([row["accuracy"] or 0.0 for row in rows], dtype=np.float64)
        return cls(
            bins=len(rows),
            count=count,
            confidence=mean * count,
            correct=np.rint(accuracy * count).astype(np.int64),
        )
