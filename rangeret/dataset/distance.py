"""Distance bands: how far each point lies from the sensor, for results broken down by distance.

A point's range is its Euclidean distance from the sensor, sqrt(x² + y² + z²), computed in float32
as the projection computes it, so a band found from a scan file equals the band found from its
projection. The bands are 0-10, 10-20, 20-30, 30-40, 40-50 and 50+ m; each includes its lower
edge, so a point at exactly 10 m lies in 10-20.
"""

from __future__ import annotations

import numpy as np

#: Lower edges of the distance bands in metres; the last band has no upper edge.
BAND_EDGES_M: tuple[int, ...] = (0, 10, 20, 30, 40, 50)

#: Number of distance bands.
NUM_BANDS = len(BAND_EDGES_M)

_UPPER = np.asarray(BAND_EDGES_M[1:], dtype=np.float32)


def point_ranges(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Euclidean range of each point in float32 from its x, y and z (the projection's depth)."""
    x, y, z = (np.asarray(a, dtype=np.float32) for a in (x, y, z))
    return np.sqrt(x * x + y * y + z * z)


def distance_bands(ranges: np.ndarray) -> np.ndarray:
    """Band index (uint8, 0..NUM_BANDS - 1) of each range; lower edges belong to their band."""
    ranges = np.asarray(ranges, dtype=np.float32).reshape(-1)
    return np.searchsorted(_UPPER, ranges, side="right").astype(np.uint8)


def scan_bands(points: np.ndarray) -> np.ndarray:
    """Band index of every point of an (N, fields) scan whose first three values are x, y, z."""
    points = np.asarray(points)
    return distance_bands(point_ranges(points[:, 0], points[:, 1], points[:, 2]))


def band_limits(band: int) -> tuple[int, int | None]:
    """(min_m, max_m) of a band; max_m is None for the last, open band."""
    upper = BAND_EDGES_M[band + 1] if band + 1 < NUM_BANDS else None
    return BAND_EDGES_M[band], upper


def band_name(band: int) -> str:
    """'10-20 m', or '50+ m' for the last band: for tables and plots."""
    low, high = band_limits(band)
    return f"{low}+ m" if high is None else f"{low}-{high} m"
