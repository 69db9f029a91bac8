"""One labelled scan resampled to another sensor: the points the target sensor's beams and pixels
would keep, moved into its frame, in its point record, with their labels.

Resampling can only thin and re-grid what the source measured: a point is kept when it lies in a
target beam's band and wins its target pixel; nothing is invented, so target beams outside the
source's field of view stay empty (`unmeasured_beams`) and occlusion differences of another
mounting point are not modelled. Pure numpy, one scan at a time, for any driver.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from rangeret.dataset.beams import beam_band, beam_elevations, beam_values, nearest_beams
from rangeret.dataset.distance import point_ranges
from rangeret.dataset.label_map import LabelMap, target_labels
from rangeret.dataset.profiles import DatasetProfile
from rangeret.dataset.projection import project
from rangeret.exceptions import InputError

#: The fifth values of a target record that adapting can fill: the beam of each point.
BEAM_FIELDS = (("laser_id",), ("ring",))


class AdaptError(InputError, ValueError):
    """An adaptation that cannot be made: profiles, an offset or a scan that do not fit it."""


@dataclass(frozen=True)
class AdaptStats:
    """What became of a scan's points (or of many scans', summed with `+`)."""

    scans: int = 0
    points_in: int = 0
    points_kept: int = 0
    #: Points whose elevation lies in no target beam's band (outside its field of view).
    dropped_fov: int = 0
    #: Points at the sensor's origin or beyond the target's max_range.
    dropped_range: int = 0
    #: Points that lost their target pixel to a point nearer its centre.
    dropped_collisions: int = 0
    #: Scans of which no point is kept (the tree leaves them out).
    empty_scans: int = 0

    def __add__(self, other: AdaptStats) -> AdaptStats:
        return AdaptStats(**{k: v + getattr(other, k) for k, v in asdict(self).items()})

    def to_dict(self) -> dict[str, int]:
        """The counts as adapt.json records them."""
        return asdict(self)


def check_profiles(source: DatasetProfile, target: DatasetProfile) -> None:
    """An `AdaptError` in one sentence unless both profiles are folder layouts and the target's
    point record holds nothing but x, y, z, the reflectance and maybe its beam."""
    for role, profile in (("source", source), ("target", target)):
        if profile.layout.folders is None:
            raise AdaptError(
                f"the {role} profile {profile.name} reads a version's tables; adapting a dataset "
                "of tables comes later, only folder layouts are adapted for now"
            )
    extra = target.points.fields[4:]
    if extra and extra not in BEAM_FIELDS:
        raise AdaptError(
            f"the target profile {target.name}'s point field {extra[0]!r} cannot be made from "
            "the source's points (only laser_id or ring, the beam, can)"
        )


def check_offset(offset: Sequence[float]) -> tuple[float, float, float]:
    """The sensor offset as three finite floats; an `AdaptError` naming it otherwise."""
    values = [float(v) for v in offset]
    if len(values) != 3 or not np.isfinite(values).all():
        raise AdaptError(f"the sensor offset must be three finite numbers (m), got {list(offset)}")
    return values[0], values[1], values[2]


def unmeasured_beams(source: DatasetProfile, target: DatasetProfile) -> list[int]:
    """The target beams whose elevation lies above the source's fov_up or below its fov_down:
    the source never measured there, so they stay empty."""
    p = source.projection
    angles = beam_elevations(target)
    outside = (angles > abs(p.fov_up)) | (angles < -abs(p.fov_down))
    return np.flatnonzero(outside).tolist()


def adapt_scan(
    points: np.ndarray,
    labels: np.ndarray,
    source: DatasetProfile,
    target: DatasetProfile,
    offset: Sequence[float] = (0.0, 0.0, 0.0),
    label_map: LabelMap | None = None,
    *,
    scan: str = "<scan>",
) -> tuple[np.ndarray, np.ndarray, AdaptStats]:
    """A source scan as the target sensor, sitting at `offset` in the source's frame, would keep
    it: (float32 points in the target's record, uint32 raw labels, counts).

    Each point moves by -offset; it is kept when its elevation lies in a target beam's band and
    its range in (0, max_range]; its pixel is the target's pitch projection of it (for uneven
    `beam_angles`: the nearest beam's row), and of several points on one pixel the one nearest
    the pixel's centre direction wins (equal: the lower index). Points keep the source's order;
    `scan` names the scan in errors (an unknown raw id, a wrong shape).
    """
    points = np.asarray(points)
    n = len(points)
    if points.ndim != 2 or points.shape[1] != source.points.num_fields:
        raise AdaptError(
            f"{scan}: points must have shape (N, {source.points.num_fields}) for the "
            f"{source.name} profile, got {points.shape}"
        )
    labels = np.asarray(labels)
    if labels.shape != (n,):
        raise AdaptError(f"{scan}: {labels.size} labels for {n} points")
    raw = target_labels(labels, target, label_map, scan)

    xyz = points[:, :3].astype(np.float32) - np.asarray(check_offset(offset), dtype=np.float32)
    exact = xyz.astype(np.float64)
    distance = np.sqrt((exact * exact).sum(axis=1))
    in_range = point_ranges(xyz[:, 0], xyz[:, 1], xyz[:, 2]) > 0
    if target.max_range is not None:
        in_range &= distance <= target.max_range
    elevation = np.degrees(np.arctan2(exact[:, 2], np.hypot(exact[:, 0], exact[:, 1])))
    low, high = beam_band(target)
    candidates = np.flatnonzero(in_range & (elevation >= low) & (elevation <= high))

    p = target.projection
    moved = np.zeros((candidates.size, 4), dtype=np.float32)
    moved[:, :3] = xyz[candidates]
    projection = project(moved, p.height, p.width, p.fov_up, p.fov_down)
    columns = projection.proj_x
    if target.beam_angles is None:
        rows = projection.proj_y
    else:
        rows = nearest_beams(elevation[candidates], target)

    # The winner of each pixel: the smallest angle to its centre direction (haversine of the
    # angle, which grows with it), then the lower index.
    centre_azimuth = np.pi - (columns + 0.5) * (2 * np.pi / p.width)
    centre_elevation = np.radians(beam_elevations(target)[rows])
    azimuth = np.arctan2(exact[candidates, 1], exact[candidates, 0])
    lat = np.radians(elevation[candidates])
    angle = (
        np.sin((lat - centre_elevation) / 2) ** 2
        + np.cos(lat) * np.cos(centre_elevation) * np.sin((azimuth - centre_azimuth) / 2) ** 2
    )
    pixel = rows * p.width + columns
    order = np.lexsort((candidates, angle, pixel))
    first = np.ones(order.size, dtype=bool)
    first[1:] = pixel[order[1:]] != pixel[order[:-1]]
    winners = np.sort(order[first])
    kept = candidates[winners]

    out = np.empty((kept.size, target.points.num_fields), dtype=np.float32)
    out[:, :3] = xyz[kept]
    reflectance = points[kept, 3]
    if target.reflectance_max != source.reflectance_max:
        scale = target.reflectance_max / source.reflectance_max
        reflectance = reflectance.astype(np.float64) * scale
    out[:, 3] = reflectance
    if target.points.num_fields == 5:
        out[:, 4] = beam_values(rows[winners], target)
    in_range_count = int(in_range.sum())
    stats = AdaptStats(
        scans=1,
        points_in=n,
        points_kept=int(kept.size),
        dropped_fov=in_range_count - int(candidates.size),
        dropped_range=n - in_range_count,
        dropped_collisions=int(candidates.size - kept.size),
        empty_scans=int(kept.size == 0),
    )
    return out, raw[kept], stats
