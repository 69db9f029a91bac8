"""Comparing evaluation reports side by side, for ablations: `rangeret compare A.json B.json ...`.

Each report's per-class IoU, mIoU and accuracy (percent) are set next to each other, and every
report after the first gets its difference from the first, in percentage points. Reports are the
JSON of `rangeret evaluate --json`, the Ray job's `--report` or a gateway job's report; they must
be of one profile and evaluate the same classes, or the comparison is refused in one sentence.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangeret.dataset.fields import is_number
from rangeret.dataset.profiles import LEGACY_PROFILE
from rangeret.exceptions import InputError


class ComparisonError(InputError, ValueError):
    """Reports that cannot be read or compared; the message names the file."""


@dataclass(frozen=True)
class ReportScores:
    """What a comparison takes from one report: its file, profile, per-class IoU, mIoU and
    accuracy (fractions 0..1)."""

    path: Path
    profile: str
    iou: dict[str, float]
    miou: float
    accuracy: float


def read_scores(path: Path | str) -> ReportScores:
    """The scores of a JSON evaluation report; `ComparisonError` for a file that is not one."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ComparisonError(f"{path} does not exist") from None
    except RecursionError:
        raise ComparisonError(
            f"{path} is not a JSON evaluation report (it nests too deeply)"
        ) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ComparisonError(f"{path} is not a JSON evaluation report ({exc})") from None
    if not isinstance(data, dict):
        raise ComparisonError(f"{path} is not a JSON evaluation report (not a JSON object)")
    iou = data.get("iou")
    numbers = [data.get("miou"), data.get("accuracy"), *(iou.values() if iou else [])]
    if not (isinstance(iou, dict) and iou and all(is_number(v) for v in numbers)):
        raise ComparisonError(
            f"{path} is not an evaluation report: it needs numbers `miou`, `accuracy` and an "
            "`iou` object of per-class numbers"
        )
    return ReportScores(
        path=path,
        profile=str(data.get("profile") or LEGACY_PROFILE),
        iou={str(name): float(value) for name, value in iou.items()},
        miou=float(data["miou"]),
        accuracy=float(data["accuracy"]),
    )


@dataclass(frozen=True)
class Comparison:
    """Reports of one profile and one set of classes, the first being the baseline."""

    reports: list[ReportScores]

    @property
    def classes(self) -> list[str]:
        """The evaluated classes, in the reports' order."""
        return list(self.reports[0].iou)

    @property
    def labels(self) -> list[str]:
        """A short, distinct name per report: the fewest trailing parts of its path (no .json)."""
        return report_labels([r.path for r in self.reports])

    def rows(self) -> list[tuple[str, list[float]]]:
        """(row name, value of each report in percent): every class, then mIoU and accuracy."""
        rows = [(c, [100 * r.iou[c] for r in self.reports]) for c in self.classes]
        rows.append(("mIoU", [100 * r.miou for r in self.reports]))
        rows.append(("accuracy", [100 * r.accuracy for r in self.reports]))
        return rows

    def table(self) -> str:
        """The table: per class (then mIoU and accuracy) each report's value in percent and, after
        every report but the first, its difference from the first in percentage points."""
        labels = self.labels
        rows = self.rows()
        width = max(len(name) for name, _ in rows)
        cols = [max(7, len(label)) for label in labels]
        head = [f"{'':<{width}}", f"{labels[0]:>{cols[0]}}"]
        for label, col in zip(labels[1:], cols[1:], strict=True):
            head += [f"{label:>{col}}", f"{'delta':>7}"]
        lines = [
            f"IoU in %; delta: difference from {labels[0]} in percentage points",
            "  ".join(head),
        ]
        for i, (name, values) in enumerate(rows):
            if i == len(rows) - 2:
                lines.append("-" * len(lines[1]))
            cells = [f"{name:<{width}}", f"{values[0]:>{cols[0]}.2f}"]
            for value, col in zip(values[1:], cols[1:], strict=True):
                cells += [f"{value:>{col}.2f}", f"{value - values[0]:>+7.2f}"]
            lines.append("  ".join(cells))
        return "\n".join(lines)

    def write_png(self, path: Path | str) -> Path:
        """Grouped bars of every report's per-class IoU and mIoU, written as a PNG at `path`."""
        from rangeret.evaluation.plots import plot_iou_comparison

        rows = self.rows()[:-1]  # accuracy is not an IoU: it stays in the table
        values = np.array([v for _, v in rows]).T
        return plot_iou_comparison(self.labels, [n for n, _ in rows], values, path)


def compare_reports(paths: list[Path | str]) -> Comparison:
    """Read two or more reports and check they compare: one profile, the same classes."""
    if len(paths) < 2:
        raise ComparisonError(f"a comparison needs at least two reports, got {len(paths)}")
    reports = [read_scores(p) for p in paths]
    first = reports[0]
    for other in reports[1:]:
        if other.profile != first.profile:
            raise ComparisonError(
                f"{other.path} is a report of the {other.profile} profile and {first.path} of "
                f"the {first.profile} profile: only reports of one profile compare"
            )
        if list(other.iou) != list(first.iou):
            raise ComparisonError(
                f"{other.path} evaluates other classes than {first.path} "
                f"({len(other.iou)} and {len(first.iou)} classes): they do not compare"
            )
    return Comparison(reports)


def report_labels(paths: list[Path]) -> list[str]:
    """The fewest trailing path parts that tell the reports apart, without `.json`; a path given
    twice gets its position appended."""
    longest = max(len(p.parts) for p in paths)
    for k in range(1, longest + 1):
        tails = ["/".join(p.parts[-k:]).removesuffix(".json") for p in paths]
        if len(set(tails)) == len(tails):
            return tails
    return [f"{tail} ({i + 1})" for i, tail in enumerate(tails)]
