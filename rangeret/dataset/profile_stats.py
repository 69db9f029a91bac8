"""A sensor's input normalisation and projection checks, measured on its data.

The five input channels (range, x, y, z, reflectance) are normalised by a profile's `means` and
`stds`, defined over the filled pixels of the range images: each pixel's winning point, as
`project_with` keeps it, with its raw values (before any normalisation). `profile_stats` streams
a dataset's scans once and returns those moments, exact to float64 rounding (per-scan moments
merged with Chan's formula), with the numbers that tell whether the projection fits the sensor:
points per scan, the share that win a pixel, laser ids or points outside the vertical field of
view. Torch-free.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from rangeret.dataset.layout import DatasetLayoutError, ScanEntry, discover
from rangeret.dataset.profiles import DatasetProfile, ProfileError
from rangeret.dataset.projection import BEAM_ROWS, ProjectionConfig, project_with
from rangeret.io.scans import read_scan

#: Above this share of points outside the vertical field of view, the summary flags the fov.
FOV_WARNING_SHARE = 0.01


@dataclass(frozen=True)
class ProfileStats:
    """What `profile_stats` measured: channel moments over the winning points, and the counts
    that check the profile's projection against the data."""

    profile: str
    row: str
    channels: tuple[str, ...]
    means: tuple[float, ...]
    stds: tuple[float, ...]
    scans: int
    points: int
    min_points: int
    max_points: int
    pixels: int
    image_pixels: int
    laser_ids: tuple[int, int] | None = None
    distinct_laser_ids: int | None = None
    above_fov: int | None = None
    below_fov: int | None = None
    pitch_range: tuple[float, float] | None = None

    @property
    def points_per_scan(self) -> float:
        """Mean number of points of a scan."""
        return self.points / self.scans

    @property
    def pixel_share(self) -> float:
        """Share of the points that win a pixel (the others are hidden behind a closer point)."""
        return self.pixels / self.points if self.points else 0.0

    @property
    def fill(self) -> float:
        """Share of the range images' pixels that hold a point."""
        return self.pixels / self.image_pixels

    @property
    def outside_fov_share(self) -> float | None:
        """Share of the points whose pitch lies outside the vertical field of view (pitch rows)."""
        if self.above_fov is None or self.below_fov is None:
            return None
        return (self.above_fov + self.below_fov) / self.points if self.points else 0.0

    def to_dict(self) -> dict[str, Any]:
        """Plain data for `--json`, the derived shares included."""
        data = asdict(self)
        data.update(
            points_per_scan=self.points_per_scan,
            pixel_share=self.pixel_share,
            fill=self.fill,
            outside_fov_share=self.outside_fov_share,
        )
        return {k: list(v) if isinstance(v, tuple) else v for k, v in data.items()}

    def profile_lines(self) -> str:
        """The `sensor.means` / `sensor.stds` YAML lines to paste into a profile (6 significant
        digits; a constant channel, whose std is 0, gets std 1 as a profile needs it positive)."""
        import yaml

        means = [float(f"{m:.6g}") for m in self.means]
        stds = [float(f"{s:.6g}") if s > 0 else 1.0 for s in self.stds]
        return yaml.safe_dump(
            {"sensor": {"means": means, "stds": stds}}, sort_keys=False, default_flow_style=None
        )

    def text(self) -> str:
        """A readable summary, ending with the YAML lines of `profile_lines`."""
        lines = [
            f"{self.scans} scans, {self.points:,} points, profile {self.profile} "
            f"(rows from {self.row})",
            f"points per scan:  {self.points_per_scan:,.0f} (min {self.min_points:,}, "
            f"max {self.max_points:,})",
            f"on a pixel:       {self.pixel_share:.1%} of the points win a pixel; "
            f"the images are {self.fill:.1%} filled",
        ]
        if self.laser_ids is not None:
            low, high = self.laser_ids
            lines.append(f"laser ids:        {low}..{high} ({self.distinct_laser_ids} distinct)")
        share = self.outside_fov_share
        if share is not None and self.pitch_range is not None:
            low, high = self.pitch_range
            lines.append(
                f"outside the fov:  {share:.2%} of the points ({self.above_fov:,} above fov_up, "
                f"{self.below_fov:,} below fov_down); pitch {low:.2f}..{high:.2f} degrees"
            )
            if share > FOV_WARNING_SHARE:
                lines.append(
                    f"{'':18s}too many: check the profile's fov_up and fov_down against it"
                )
        lines += ["", f"{'channel':10s} {'mean':>12s} {'std':>12s}   (over {self.pixels:,} pixels)"]
        for name, mean, std in zip(self.channels, self.means, self.stds, strict=True):
            lines.append(f"{name:10s} {mean:12.6g} {std:12.6g}")
        if any(not s > 0 for s in self.stds):
            lines.append("a channel is constant (std 0): its std is written as 1 below")
        lines += ["", "for the profile (sensor section):", self.profile_lines().rstrip("\n")]
        return "\n".join(lines)


class _Moments:
    """Count, mean and centred sum of squares of the rows of float64 blocks, merged block by
    block (Chan et al.), so the result is exact to float64 rounding however many blocks come."""

    def __init__(self, width: int) -> None:
        self.count = 0
        self.mean = np.zeros(width, dtype=np.float64)
        self.m2 = np.zeros(width, dtype=np.float64)

    def add(self, values: np.ndarray) -> None:
        n = values.shape[0]
        if n == 0:
            return
        mean = values.mean(axis=0)
        m2 = ((values - mean) ** 2).sum(axis=0)
        total = self.count + n
        delta = mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + m2 + delta * delta * (self.count * n / total)
        self.count = total

    def std(self) -> np.ndarray:
        """Population standard deviation (divided by the count)."""
        return np.sqrt(self.m2 / self.count) if self.count else np.zeros_like(self.m2)


def _fov_rows(points: np.ndarray, config: ProjectionConfig) -> tuple[np.ndarray, np.ndarray]:
    """Unclamped rows (float32, as `project_with` computes them) and pitches (radians) of the
    points that have a range."""
    cols = np.ascontiguousarray(points[:, :3].astype(np.float32, copy=False).T)
    x, y, z = cols
    with np.errstate(invalid="ignore", over="ignore"):
        depth = np.sqrt(x * x + y * y + z * z)
    keep = np.isfinite(depth) & (depth > 0)
    z, depth = z[keep], depth[keep]
    fov_up = abs(config.fov_up) / 180.0 * np.pi
    fov_down = abs(config.fov_down) / 180.0 * np.pi
    fov = np.float32(fov_down + fov_up)
    pitch = np.arcsin(np.clip(z / depth, np.float32(-1), np.float32(1)))
    v = (np.float32(1.0) - (pitch + np.float32(fov_down)) / fov) * np.float32(config.height)
    return v, pitch


def _chosen(scans: Sequence[ScanEntry], max_scans: int | None) -> list[ScanEntry]:
    """All scans, or `max_scans` of them spread evenly over the selection (first one included)."""
    if max_scans is None or max_scans >= len(scans):
        return list(scans)
    return [scans[i * len(scans) // max_scans] for i in range(max_scans)]


def profile_stats(
    root: str | os.PathLike[str],
    sequences: Sequence[str],
    profile: DatasetProfile,
    max_scans: int | None = None,
    progress: bool = False,
) -> ProfileStats:
    """Channel means and stds over the winning points of the scans of `sequences` under `root`
    (in the profile's layout and point record), with the projection's checks; `max_scans` takes
    that many scans spread evenly over the selection."""
    if max_scans is not None and max_scans < 1:
        raise ProfileError(f"--max-scans must be at least 1, got {max_scans}")
    found = discover(Path(root), sequences, layout=profile.layout)
    if found.problems:
        raise DatasetLayoutError("; ".join(found.problems))
    if not found.scans:
        raise DatasetLayoutError(f"no scans of sequences {', '.join(sequences)} under {root}")
    scans = _chosen(found.scans, max_scans)
    config = profile.projection
    laser_rows = config.row in BEAM_ROWS
    moments = _Moments(5)
    points_total = pixels = 0
    counts: list[int] = []
    lasers: set[int] = set()
    above = below = 0
    pitch_low, pitch_high = np.inf, -np.inf
    for entry in tqdm(scans, desc="profile stats", unit="scan", disable=not progress):
        points = read_scan(entry.scan_path, profile.points)
        try:
            proj = project_with(points, config)
        except ValueError as exc:
            hint = f" (sensor.height is {config.height})" if laser_rows else ""
            raise ProfileError(f"{entry.scan_path}: {exc}{hint}") from exc
        winners = proj.proj_idx[proj.mask]
        values = np.empty((winners.size, 5), dtype=np.float64)
        values[:, 0] = proj.proj_range[proj.mask]
        values[:, 1:] = points[winners, :4]
        moments.add(values)
        counts.append(len(points))
        points_total += len(points)
        pixels += int(winners.size)
        if laser_rows:
            lasers.update(np.unique(points[:, 4].astype(np.int32)).tolist())
        else:
            v, pitch = _fov_rows(points, config)
            above += int(np.count_nonzero(v < 0))
            below += int(np.count_nonzero(v >= config.height))
            if pitch.size:
                pitch_low = min(pitch_low, float(pitch.min()))
                pitch_high = max(pitch_high, float(pitch.max()))
    record = profile.points.fields
    return ProfileStats(
        profile=profile.name,
        row=config.row,
        channels=("range", "x", "y", "z", record[3]),
        means=tuple(float(m) for m in moments.mean),
        stds=tuple(float(s) for s in moments.std()),
        scans=len(scans),
        points=points_total,
        min_points=min(counts),
        max_points=max(counts),
        pixels=pixels,
        image_pixels=len(scans) * config.height * config.width,
        laser_ids=(min(lasers), max(lasers)) if laser_rows else None,
        distinct_laser_ids=len(lasers) if laser_rows else None,
        above_fov=None if laser_rows else above,
        below_fov=None if laser_rows else below,
        pitch_range=None
        if laser_rows or pitch_low > pitch_high
        else (float(np.degrees(pitch_low)), float(np.degrees(pitch_high))),
    )
