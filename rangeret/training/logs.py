"""The run's logs: `steps.csv` (loss and lr of every step), `metrics.csv` (one row per epoch) and
`curves.png` (the training curves drawn from both).

Rows are appended when the run saves its state, so the files always end where the saved state
does; a resumed run first cuts them back to that point (rows of a crashed stretch go away).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np


class CsvLog:
    """An append-only CSV with a fixed header, cut back to a step on resume."""

    def __init__(self, path: Path, fields: Sequence[str]) -> None:
        self.path = path
        self.fields = list(fields)

    def start(self, keep_until: int | None, key: str = "step") -> None:
        """Start the file: a fresh one, or (resuming) the rows whose `key` is at most `keep_until`."""
        rows = self.read() if keep_until is not None and self.path.exists() else []
        kept = [
            r for r in rows if r.get(key) not in (None, "") and int(float(r[key])) <= keep_until
        ]
        with self.path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(kept)

    def append(self, rows: Sequence[Mapping[str, Any]]) -> None:
        """Append rows (missing fields stay empty)."""
        if not rows:
            return
        with self.path.open("a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields, extrasaction="ignore")
            writer.writerows([{k: _cell(v) for k, v in row.items()} for row in rows])

    def read(self) -> list[dict[str, str]]:
        """All rows as dicts of strings."""
        with self.path.open(newline="") as f:
            return list(csv.DictReader(f))


def metrics_columns(losses: Sequence[str], validation: Sequence[str]) -> list[str]:
    """The columns of metrics.csv: epoch, step, lr, time, the training loss and its `losses`
    terms, the training mIoU and the `validation` metrics."""
    return [
        "epoch",
        "step",
        "lr",
        "seconds",
        "train_loss",
        *(f"train_{n}" for n in losses),
        "train_miou_image",
        *validation,
    ]


def _cell(value: Any) -> Any:
    """Floats with enough digits to read back exactly; everything else as is."""
    return repr(float(value)) if isinstance(value, float) else value


def _column(rows: Sequence[Mapping[str, str]], name: str) -> list[float]:
    return [float(r[name]) if r.get(name) not in (None, "") else math.nan for r in rows]


def _running_mean(values: Sequence[float], window: int) -> np.ndarray:
    """Mean of each value and the `window - 1` before it (fewer at the start)."""
    sums = np.concatenate([[0.0], np.cumsum(values)])
    ends = np.arange(1, len(values) + 1)
    starts = np.maximum(ends - window, 0)
    return (sums[ends] - sums[starts]) / (ends - starts)


def plot_curves(steps_csv: Path, metrics_csv: Path, path: Path) -> Path:
    """Draw loss, mIoU and learning-rate curves from the two CSVs into a PNG at `path`.

    Uses matplotlib's Agg canvas directly, so no global backend is set and no display is needed.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    steps = CsvLog(steps_csv, []).read() if steps_csv.exists() else []
    epochs = CsvLog(metrics_csv, []).read() if metrics_csv.exists() else []
    fig = Figure(figsize=(15, 4.5))
    FigureCanvasAgg(fig)
    ax_loss, ax_miou, ax_lr = fig.subplots(1, 3)

    step_x = _column(steps, "step")
    losses = _column(steps, "loss")
    ax_loss.plot(step_x, losses, color="0.75", linewidth=0.7, label="train (step)")
    window = max(1, len(losses) // 50)
    if window > 1:
        ax_loss.plot(
            step_x, _running_mean(losses, window), color="C0", label=f"train (mean of {window})"
        )
    epoch_x = _column(epochs, "step")
    ax_loss.plot(epoch_x, _column(epochs, "train_loss"), "o-", color="C1", label="train (epoch)")
    if any(not math.isnan(v) for v in _column(epochs, "val_loss")):
        ax_loss.plot(epoch_x, _column(epochs, "val_loss"), "s-", color="C3", label="validation")
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("loss")
    ax_loss.set_title("Loss")
    ax_loss.legend()

    for name, label in (
        ("train_miou_image", "train, range image"),
        ("val_miou_image", "validation, range image"),
        ("val_miou_points", "validation, points"),
        ("val_miou_knn", "validation, points + kNN"),
    ):
        values = [100 * v for v in _column(epochs, name)]
        if any(not math.isnan(v) for v in values):
            ax_miou.plot(epoch_x, values, "o-", label=label)
    ax_miou.set_xlabel("step")
    ax_miou.set_ylabel("mIoU (%)")
    ax_miou.set_title("mIoU at the end of each epoch")
    if ax_miou.lines:
        ax_miou.legend()

    ax_lr.plot(step_x, _column(steps, "lr"), color="C2")
    ax_lr.set_xlabel("step")
    ax_lr.set_ylabel("learning rate")
    ax_lr.set_title("Learning rate")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path
