"""PNG plots of an evaluation: the row-normalised confusion matrix, per-class IoU bars, per-class
IoU by distance band (a heat map) and mIoU per sequence (bars)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangeret.dataset.distance import band_name
from rangeret.dataset.labels import LabelConfig
from rangeret.evaluation.calibration import Calibration
from rangeret.evaluation.metrics import EvaluationReport


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_confusion(report: EvaluationReport, path: Path | str) -> Path:
    """Confusion matrix of the evaluated classes, each ground-truth row normalised to 1 (recall)."""
    plt = _pyplot()
    include = report.confusion.include
    names = [report.class_names[c] for c in include]
    gt_by_pred = report.confusion.matrix[np.ix_(include, include)].T.astype(np.float64)
    rows = gt_by_pred.sum(axis=1, keepdims=True)
    norm = np.divide(gt_by_pred, rows, out=np.zeros_like(gt_by_pred), where=rows > 0)

    fig, ax = plt.subplots(figsize=(10, 9))
    im = ax.imshow(norm, cmap="Blues", vmin=0, vmax=1)
    ax.set_xticks(range(len(names)), names, rotation=60, ha="right")
    ax.set_yticks(range(len(names)), names)
    ax.set_xlabel("predicted class")
    ax.set_ylabel("ground-truth class")
    ax.set_title(f"Confusion matrix (rows normalised), mIoU {100 * report.miou:.1f} %")
    for i in range(len(names)):
        for j in range(len(names)):
            if norm[i, j] >= 0.005:
                ax.text(
                    j,
                    i,
                    f"{100 * norm[i, j]:.0f}",
                    ha="center",
                    va="center",
                    fontsize=6,
                    color="white" if norm[i, j] > 0.5 else "black",
                )
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="share of the ground-truth class")
    fig.tight_layout()
    return _save(fig, path)


def _value(percent: float) -> str:
    """A bar's label: the value with one decimal, or n/a where it is undefined (NaN)."""
    return "n/a" if np.isnan(percent) else f"{percent:.1f}"


def plot_iou(report: EvaluationReport, path: Path | str, *, config: LabelConfig) -> Path:
    """Bar chart of per-class IoU in the classes' colours (the label configuration's), with the
    mIoU line; a class absent from the data (no point predicted or labelled) is a grey hatched
    column marked "absent", not a bar at 0."""
    plt = _pyplot()
    include = report.confusion.include
    iou = report.confusion.iou()[include] * 100
    tp, fp, fn = report.confusion.stats()
    absent = (tp + fp + fn)[include] == 0
    colours = (
        config.class_rgb()[include] / 255.0
        if config.num_classes == len(report.class_names)
        else np.tile([0.27, 0.51, 0.71], (len(include), 1))
    )

    fig, ax = plt.subplots(figsize=(11, 4.5))
    x = np.arange(len(include))
    bars = ax.bar(x[~absent], iou[~absent], color=colours[~absent], edgecolor="black", lw=0.5)
    ax.bar_label(bars, labels=[_value(v) for v in iou[~absent]], fontsize=7, padding=2)
    if absent.any():
        ax.bar(x[absent], 100, color="0.92", edgecolor="0.6", hatch="//", lw=0.5, label="absent")
        for i in x[absent]:
            ax.text(i, 50, "absent", rotation=90, ha="center", va="center", fontsize=7, color="0.4")
    ax.axhline(
        100 * report.miou, color="crimson", linestyle="--", label=f"mIoU {100 * report.miou:.1f} %"
    )
    ax.set_xticks(
        range(len(include)), [report.class_names[c] for c in include], rotation=60, ha="right"
    )
    ax.set_ylim(0, 100)
    ax.set_ylabel("IoU (%)")
    scans = f"{report.num_scans:,} scan{'' if report.num_scans == 1 else 's'}"
    ax.set_title(f"Per-class IoU over {scans}")
    ax.legend(loc="upper right")
    fig.tight_layout()
    return _save(fig, path)


def plot_iou_by_distance(report: EvaluationReport, path: Path | str) -> Path:
    """Heat map of each evaluated class's IoU in each distance band, with each band's mIoU and
    points; a class absent from a band (no point predicted or labelled) is left grey."""
    plt = _pyplot()
    include = report.confusion.include
    bands = report.by_distance
    iou = np.full((len(include), len(bands)), np.nan)
    for b, cm in enumerate(bands):
        tp, fp, fn = cm.stats()
        seen = (tp + fp + fn)[include] > 0
        iou[seen, b] = 100 * cm.iou()[include][seen]

    fig, ax = plt.subplots(figsize=(2.2 + 1.3 * len(bands), 1.2 + 0.38 * len(include)))
    ax.set_facecolor("0.85")
    im = ax.imshow(np.ma.masked_invalid(iou), cmap="viridis", vmin=0, vmax=100, aspect="auto")
    for i in range(len(include)):
        for b in range(len(bands)):
            if not np.isnan(iou[i, b]):
                colour = "black" if iou[i, b] > 60 else "white"
                ax.text(
                    b, i, f"{iou[i, b]:.0f}", ha="center", va="center", fontsize=7, color=colour
                )
    columns = [
        f"{band_name(b)}\nmIoU {100 * cm.miou():.1f}\n{cm.evaluated_points():,} pts"
        for b, cm in enumerate(bands)
    ]
    ax.set_xticks(range(len(bands)), columns, fontsize=7)
    ax.set_yticks(range(len(include)), [report.class_names[c] for c in include], fontsize=8)
    ax.set_xlabel("distance from the sensor")
    ax.set_title("IoU (%) by distance band (grey: class absent from the band)")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="IoU (%)")
    fig.tight_layout()
    return _save(fig, path)


def plot_miou_by_sequence(report: EvaluationReport, path: Path | str) -> Path:
    """Bar chart of each sequence's mIoU, with the overall mIoU line."""
    plt = _pyplot()
    names = list(report.by_sequence)
    miou = [100 * cm.miou() for cm in report.by_sequence.values()]

    fig, ax = plt.subplots(figsize=(2.2 + 0.6 * len(names), 3.2))  # narrow for a few sequences
    bars = ax.bar(range(len(names)), miou, color="steelblue", edgecolor="black", linewidth=0.5)
    ax.bar_label(bars, labels=[_value(v) for v in miou], fontsize=7, padding=2)
    ax.axhline(
        100 * report.miou, color="crimson", linestyle="--", label=f"mIoU {100 * report.miou:.1f} %"
    )
    ax.set_xticks(range(len(names)), names)
    ax.set_xlabel("sequence")
    ax.set_ylim(0, 100)
    ax.set_ylabel("mIoU (%)")
    ax.set_title("mIoU per sequence")
    ax.legend(loc="upper right")
    fig.tight_layout()
    return _save(fig, path)


def plot_iou_comparison(
    labels: list[str], names: list[str], values: np.ndarray, path: Path | str
) -> Path:
    """Grouped bars comparing reports: `values[r, i]` is report `labels[r]`'s value (percent) of
    row `names[i]` (per-class IoU, then mIoU)."""
    plt = _pyplot()
    values = np.asarray(values, dtype=np.float64)
    reports, rows = values.shape
    width = 0.8 / reports
    fig, ax = plt.subplots(figsize=(max(6.0, 1.0 + rows * (0.25 + 0.18 * reports)), 4.8))
    colours = plt.get_cmap("tab10")
    for r in range(reports):
        offsets = np.arange(rows) - 0.4 + width * (r + 0.5)
        ax.bar(offsets, values[r], width, label=labels[r], color=colours(r % 10), linewidth=0)
    ax.axvline(rows - 1.5, color="0.5", linewidth=0.8)
    ax.set_xticks(range(rows), names, rotation=60, ha="right")
    ax.set_xlim(-0.6, rows - 0.4)
    ax.set_ylim(0, 100)
    ax.set_ylabel("IoU (%)")
    ax.set_title("Per-class IoU and mIoU of each report")
    ax.legend(loc="upper left", fontsize=8, ncols=min(reports, 4))
    fig.tight_layout()
    return _save(fig, path)


def write_plots(report: EvaluationReport, folder: Path | str, *, config: LabelConfig) -> list[Path]:
    """Write `confusion.png` and `iou.png` into `folder`, in the label configuration's colours,
    and, for a report broken down by distance and sequence, `iou-by-distance.png` and
    `miou-by-sequence.png`, and `calibration.png` where the report has confidences."""
    folder = Path(folder)
    paths = [
        plot_confusion(report, folder / "confusion.png"),
        plot_iou(report, folder / "iou.png", config=config),
    ]
    if report.by_distance:
        paths.append(plot_iou_by_distance(report, folder / "iou-by-distance.png"))
    if report.by_sequence:
        paths.append(plot_miou_by_sequence(report, folder / "miou-by-sequence.png"))
    if report.calibration is not None:
        paths.append(plot_calibration(report.calibration, folder / "calibration.png"))
    return paths


def plot_calibration(calibration: Calibration, path: Path | str) -> Path:
    """Reliability diagram: each confidence bin's accuracy against its mean confidence (a
    calibrated network lies on the diagonal), and how many points each bin holds."""
    plt = _pyplot()
    rows = calibration.to_dict()["bins"]
    centres = [(row["min"] + row["max"]) / 2 for row in rows]
    width = 1.0 / len(rows)
    accuracy = [row["accuracy"] or 0.0 for row in rows]
    fig, (ax, counts) = plt.subplots(
        2, 1, figsize=(5, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    ax.bar(centres, accuracy, width, color="steelblue", edgecolor="black", linewidth=0.5)
    ax.plot([0, 1], [0, 1], color="crimson", linestyle="--", label="calibrated")
    ax.set_ylim(0, 1)
    ax.set_ylabel("accuracy")
    ax.set_title(f"Confidence calibration (ECE {100 * calibration.ece():.2f} %)")
    ax.legend(loc="upper left")
    counts.bar(centres, [row["points"] for row in rows], width, color="0.6")
    counts.set_xlim(0, 1)
    counts.set_xlabel("confidence")
    counts.set_ylabel("points")
    fig.tight_layout()
    return _save(fig, path)


def _save(fig, path: Path | str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    fig.clf()
    import matplotlib.pyplot as plt

    plt.close(fig)
    return path


def plot_range_image(
    range_image: np.ndarray,
    ground_truth: np.ndarray | None,
    prediction: np.ndarray,
    path: Path | str,
    *,
    config: LabelConfig,
    title: str = "",
) -> Path:
    """Stacked PNG of one scan's range image (with its colour bar in metres), its ground truth and
    the prediction (training classes in the label configuration's colours, named in a legend of
    the classes shown; empty pixels black)."""
    plt = _pyplot()
    palette = config.class_rgb()
    panels: list[tuple[str, np.ndarray]] = []
    rng = np.where(range_image > 0, range_image, np.nan)
    panels.append(("input range (m)", rng))
    if ground_truth is not None:
        panels.append(("ground truth", palette[ground_truth]))
    panels.append(("prediction", palette[prediction]))
    h, w = range_image.shape
    fig, axes = plt.subplots(
        len(panels), 1, figsize=(min(20, w / 60 + 2), 1.3 * len(panels) * max(1.0, h / 64) + 0.8)
    )
    for ax, (name, data) in zip(np.atleast_1d(axes), panels, strict=True):
        if data.ndim == 2:
            ax.set_facecolor("black")
            im = ax.imshow(data, cmap="turbo", aspect="auto", interpolation="nearest")
            fig.colorbar(im, ax=ax, fraction=0.02, pad=0.01)
        else:
            ax.imshow(data, aspect="auto", interpolation="nearest")
        ax.set_title(name, fontsize=9, loc="left")
        ax.set_xticks([])
        ax.set_yticks([])
    shown = np.unique(
        np.concatenate(
            [prediction.ravel(), *([ground_truth.ravel()] if ground_truth is not None else [])]
        )
    )
    names = config.class_names
    handles = [
        plt.Rectangle((0, 0), 1, 1, color=palette[c] / 255.0, label=names[c])
        for c in shown
        if c < len(names)
    ]
    fig.legend(
        handles=handles, loc="lower center", ncol=min(len(handles), 8), fontsize=7, frameon=False
    )
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.04 + 0.035 * ((len(handles) - 1) // 8 + 1), 1, 1))
    return _save(fig, path)
