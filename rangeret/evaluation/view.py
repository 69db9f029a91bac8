"""`rangeret view`: one scan with its labels as a coloured PLY point cloud and bird's-eye PNGs.

The scan is any point-cloud file `rangeret.io.point_files` reads (`.bin` with the profile's point
record, PCD, PLY, LAS/LAZ), its fields mapped to the record as `rangeret predict --files` maps
them; points with a NaN or infinite value are left out of the view (with their labels). A label file (the prediction, the ground truth
or both) must hold one uint32 per point. Points take their raw id's colour from the profile's
palette (the label configuration's `color_map`, stored BGR as in the official YAML, written RGB);
the PLY is coloured by the prediction when there is one, else by the ground truth, else by height
in grey. The PNG has one bird's-eye panel per label file (the highest point of each cell shows)
and, with both, an error map (right, wrong, and points whose ground truth is an ignored class);
a legend names the raw ids present in their colours.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangeret.dataset.labels import SEMANTIC_MASK, LabelConfig
from rangeret.dataset.profiles import DatasetProfile
from rangeret.evaluation.plots import _pyplot
from rangeret.io.atomic import atomic_path
from rangeret.io.decode_limits import DEFAULT_LIMITS, DecodeLimits
from rangeret.io.ply import write_ply
from rangeret.io.point_fields import to_record
from rangeret.io.point_files import read_point_file
from rangeret.io.scans import LabelFile, ScanFormatError

#: Error map colours (RGB): right, wrong, ignored ground truth; and the background.
RIGHT_RGB = (44, 160, 44)
WRONG_RGB = (214, 39, 40)
IGNORED_RGB = (160, 160, 160)
BACKGROUND_RGB = (255, 255, 255)

#: Pixels along each side of a bird's-eye panel.
PANEL_PIXELS = 600


@dataclass(frozen=True)
class LabelledScan:
    """A scan's points with its prediction and ground truth (raw uint32 labels, or None)."""

    scan: Path
    points: np.ndarray
    prediction: np.ndarray | None = None
    prediction_path: Path | None = None
    ground_truth: np.ndarray | None = None
    ground_truth_path: Path | None = None
    #: Points of the file left out because a value is NaN or infinite.
    invalid_points: int = 0

    @property
    def coloured_by(self) -> str:
        """What the point cloud's colours show, for people."""
        if self.prediction is not None:
            return f"the prediction ({self.prediction_path})"
        if self.ground_truth is not None:
            return f"the ground truth ({self.ground_truth_path})"
        return "height, in grey (no label file given)"


def load_labelled_scan(
    scan: Path | str,
    labels: Path | str | None = None,
    ground_truth: Path | str | None = None,
    *,
    profile: DatasetProfile,
    overrides: dict[str, str] | None = None,
    limits: DecodeLimits = DEFAULT_LIMITS,
) -> LabelledScan:
    """Read a point-cloud file as the profile's record (`overrides`: `--field` mappings; `limits`:
    what it may decode to) and its label files, each checked to hold one uint32 per point of the
    file (a ScanFormatError naming the file and both counts otherwise); invalid points are then
    left out."""
    scan = Path(scan)
    cloud = to_record(
        read_point_file(scan, record=profile.points, limits=limits).columns,
        record=profile.points,
        source=str(scan),
        reflectance_fill=profile.reflectance_fill,
        overrides=overrides,
    )
    n, valid = cloud.num_points, cloud.valid
    label_file = profile.layout.label_file
    prediction = _labels_for(labels, scan, n, label_file)
    if prediction is not None and profile.benchmark.predictions == "class":
        prediction = profile.labels.to_raw(profile.prediction_classes(prediction))
    truth = _labels_for(ground_truth, scan, n, label_file)
    if cloud.num_invalid:
        prediction = None if prediction is None else prediction[valid]
        truth = None if truth is None else truth[valid]
    return LabelledScan(
        scan=scan,
        points=cloud.points[valid] if cloud.num_invalid else cloud.points,
        prediction=prediction,
        prediction_path=Path(labels) if labels is not None else None,
        ground_truth=truth,
        ground_truth_path=Path(ground_truth) if ground_truth is not None else None,
        invalid_points=cloud.num_invalid,
    )


def _labels_for(
    path: Path | str | None, scan: Path, num_points: int, label_file: LabelFile
) -> np.ndarray | None:
    """The labels of `path` for a scan of `num_points` points, or None without a path."""
    if path is None:
        return None
    labels = label_file.read(path)
    if len(labels) != num_points:
        raise ScanFormatError(
            path,
            f"holds {len(labels)} labels but the scan {scan} has {num_points} points "
            f"(a label file holds one uint{8 * label_file.bytes} per point)",
        )
    return labels


def raw_palette(config: LabelConfig) -> np.ndarray:
    """(65536, 3) uint8 RGB colour of every 16-bit raw id: its own palette colour, else its
    class's (the configuration stores BGR, as the official YAML's color_map)."""
    lut = config.class_rgb()[config.raw_lut]
    for raw, bgr in config.raw_bgr.items():
        lut[raw] = bgr[::-1]
    return lut


def label_colours(labels: np.ndarray, config: LabelConfig) -> np.ndarray:
    """(N, 3) uint8 RGB palette colour of each raw label (instance bits ignored)."""
    return raw_palette(config)[np.asarray(labels).astype(np.int64) & SEMANTIC_MASK]


def height_colours(z: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 grey by height, dark low to light high (2nd to 98th percentile)."""
    if len(z) == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    low, high = np.percentile(z, [2, 98])
    t = np.clip((z - low) / max(high - low, 1e-6), 0, 1)
    grey = (40 + 170 * t).astype(np.uint8)
    return np.repeat(grey[:, None], 3, axis=1)


def cloud_colours(view: LabelledScan, config: LabelConfig) -> tuple[np.ndarray, np.ndarray]:
    """The colours and raw labels (uint32, low 16 bits) the point cloud is written with."""
    labels = view.prediction if view.prediction is not None else view.ground_truth
    if labels is None:
        return height_colours(view.points[:, 2]), np.zeros(len(view.points), dtype=np.uint32)
    raw = (labels & SEMANTIC_MASK).astype(np.uint32)
    return label_colours(raw, config), raw


def write_view(view: LabelledScan, out: Path | str, profile: DatasetProfile) -> list[Path]:
    """Write `out` (.ply: the coloured cloud and its PNG beside it; .png: the PNG alone)."""
    out = Path(out)
    config = profile.labels
    written = []
    if out.suffix == ".ply":
        rgb, raw = cloud_colours(view, config)
        comments = (
            f"rangeret view of {view.scan.name}, {profile.name} profile",
            f"colours: {view.coloured_by}",
            "label: raw semantic id of each point",
        )
        written.append(write_ply(out, view.points[:, :3], rgb, raw, comments))
        out = out.with_suffix(".png")
    written.append(plot_view(view, out, config))
    return written


def bird_eye(
    xy: np.ndarray, z: np.ndarray, rgb: np.ndarray, half: float, pixels: int = PANEL_PIXELS
) -> np.ndarray:
    """(pixels, pixels, 3) uint8 top view of a square of side 2 * half around the sensor, x up
    and y left as the vehicle sees them; each cell shows its highest point's colour."""
    image = np.full((pixels, pixels, 3), BACKGROUND_RGB, dtype=np.uint8)
    row = np.floor((half - xy[:, 0]) / (2 * half) * pixels).astype(np.int64)
    col = np.floor((half - xy[:, 1]) / (2 * half) * pixels).astype(np.int64)
    inside = (row >= 0) & (row < pixels) & (col >= 0) & (col < pixels)
    order = np.flatnonzero(inside)[np.argsort(z[inside], kind="stable")][::-1]
    cells = row[order] * pixels + col[order]
    _, first = np.unique(cells, return_index=True)  # the highest point of each cell
    winners = order[first]
    image[row[winners], col[winners]] = rgb[winners]
    return image


def _extent(xy: np.ndarray) -> float:
    """Half the side of the square shown: what holds 99 % of the points, at least 1 m."""
    if len(xy) == 0:
        return 1.0
    return max(1.0, float(np.ceil(np.percentile(np.abs(xy).max(axis=1), 99))))


def view_panels(view: LabelledScan, config: LabelConfig) -> list[tuple[str, np.ndarray]]:
    """Each panel's title and per-point RGB colours: prediction, ground truth and error map, or
    height where there is no label file."""
    panels = []
    if view.prediction is not None:
        panels.append(
            (f"prediction: {view.prediction_path.name}", label_colours(view.prediction, config))
        )
    if view.ground_truth is not None:
        panels.append(
            (
                f"ground truth: {view.ground_truth_path.name}",
                label_colours(view.ground_truth, config),
            )
        )
    if view.prediction is not None and view.ground_truth is not None:
        pred, gt = config.to_class(view.prediction), config.to_class(view.ground_truth)
        ignored = np.asarray(config.ignored, dtype=bool)[gt]
        right = (pred == gt) & ~ignored
        rgb = np.where(right[:, None], RIGHT_RGB, WRONG_RGB).astype(np.uint8)
        rgb[ignored] = IGNORED_RGB
        scored = int((~ignored).sum())
        share = f"{100 * right.sum() / scored:.1f} % right" if scored else "nothing scored"
        panels.append((f"error map: {share}", rgb))
    if not panels:
        panels.append(("height (no label file given)", height_colours(view.points[:, 2])))
    return panels


def plot_view(view: LabelledScan, path: Path | str, config: LabelConfig) -> Path:
    """The bird's-eye PNG of a labelled scan: one panel per label file, the error map with both,
    and a legend of the raw ids present in the palette's colours."""
    from matplotlib.patches import Patch

    plt = _pyplot()
    panels = view_panels(view, config)
    xy, z = view.points[:, :2], view.points[:, 2]
    half = _extent(xy)
    fig, axes = plt.subplots(
        1, len(panels), figsize=(6 * len(panels) + 2.6, 6.4), squeeze=False, dpi=100
    )
    for ax, (title, rgb) in zip(axes[0], panels, strict=True):
        ax.imshow(
            bird_eye(xy, z, rgb, half),
            interpolation="nearest",
            extent=(half, -half, -half, half),
        )
        ax.set_title(title, fontsize=9, loc="left")
        ax.set_xlabel("y (m)")
        ax.set_ylabel("x (m), forward")
    handles = _legend(view, config)
    if handles:
        fig.legend(
            handles=[Patch(facecolor=np.asarray(c) / 255, label=n) for n, c in handles],
            loc="center right",
            fontsize=8,
            frameon=False,
        )
    fig.suptitle(f"{view.scan.name}: {len(view.points):,} points", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1 - 2.6 / (6 * len(panels) + 2.6), 1))
    return _save_png(fig, path)


def _legend(view: LabelledScan, config: LabelConfig) -> list[tuple[str, tuple[int, ...]]]:
    """Name and RGB colour of every raw id in the label files, then the error map's keys."""
    present = [
        labels & SEMANTIC_MASK
        for labels in (view.prediction, view.ground_truth)
        if labels is not None
    ]
    if not present:
        return []
    palette = raw_palette(config)
    raws = np.unique(np.concatenate(present))
    entries = [
        (f"{int(r)} {config.raw_names.get(int(r), 'unknown')}", tuple(int(v) for v in palette[r]))
        for r in raws
    ]
    if len(present) == 2:
        entries += [("right", RIGHT_RGB), ("wrong", WRONG_RGB), ("ignored", IGNORED_RGB)]
    return entries


def _save_png(fig, path: Path | str) -> Path:
    """Save a figure as a PNG atomically and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
