"""A profile's beams: where each is aimed, which beam a direction belongs to, and the value a
point record holds for it.

Beam i is aimed at the centre of row i of the profile's range image (the rows divide the vertical
field of view evenly, row 0 at the top), or at `sensor.beam_angles[i]` where the profile lists
its beams' elevations. A direction belongs to its nearest beam when it lies within half a beam
spacing of it (for the outer beams, half the spacing to their only neighbour) and within the
field of view. Torch-free.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from rangeret.dataset.profiles import DatasetProfile


def beam_elevations(profile: DatasetProfile) -> np.ndarray:
    """(H,) float64 elevation of each beam in degrees, top beam first: `sensor.beam_angles`, or
    the centre of each row of the profile's range image."""
    if profile.beam_angles is not None:
        return np.asarray(profile.beam_angles, dtype=np.float64)
    p = profile.projection
    top, bottom = abs(p.fov_up), -abs(p.fov_down)
    row = (top - bottom) / p.height
    return top - (np.arange(p.height) + 0.5) * row


def beam_band(profile: DatasetProfile) -> tuple[float, float]:
    """The (lowest, highest) elevation in degrees that a beam of the profile takes: half a beam
    spacing beyond its outer beams, within its field of view."""
    p = profile.projection
    top, bottom = abs(p.fov_up), -abs(p.fov_down)
    angles = beam_elevations(profile)
    if angles.size < 2:
        return bottom, top
    high = angles[0] + (angles[0] - angles[1]) / 2
    low = angles[-1] - (angles[-2] - angles[-1]) / 2
    return max(bottom, float(low)), min(top, float(high))


def nearest_beams(elevations: np.ndarray, profile: DatasetProfile) -> np.ndarray:
    """(N,) int64 index of the beam nearest to each elevation (degrees); a direction half-way
    between two beams goes to the upper one."""
    angles = beam_elevations(profile)
    if angles.size < 2:
        return np.zeros(np.shape(elevations), dtype=np.int64)
    # Angles decrease with the index: a direction lies below the midpoints of the beams above it.
    midpoints = (angles[:-1] + angles[1:]) / 2
    return np.searchsorted(-midpoints, -np.asarray(elevations, dtype=np.float64), side="left")


def beam_values(lasers: np.ndarray, profile: DatasetProfile) -> np.ndarray:
    """The fifth record value of points from their beam indices (0 = the top beam), float32: the
    index itself for a `laser_id` record, the ring counted from the lowest beam of the profile's
    image for a `ring` record, as Velodyne numbers them."""
    lasers = np.asarray(lasers)
    if profile.points.fields[4:] == ("ring",):
        lasers = profile.projection.height - 1 - lasers
    return lasers.astype(np.float32)
