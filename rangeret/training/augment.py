"""The thesis's point-cloud augmentations (section 3.4, Algorithm 2), applied before projection.

In this order: random scale of x and y by one factor drawn from [0.95, 1.05]; rotation about z by
an angle drawn from [0, 360) degrees; one (x, y) shift per scan drawn from N(0, 0.3 m) and clipped
to +-0.3 m ("jitter" in the thesis); a flip of x, y, both or neither (each with probability 1/4).
z, the reflectance and any further value (a laser id) are never changed, no point is added,
dropped or reordered, so a point's label (same index) goes wherever the point goes. Points that the projection leaves out (at the origin
or not finite) are left as they are, so that they stay out.
"""

from __future__ import annotations

import numpy as np

#: Half-width of the scale range (Algorithm 2's SCALE_RATE): factors in [0.95, 1.05].
SCALE_RATE = 0.05
#: Standard deviation and clip of the per-scan (x, y) shift in metres (Algorithm 2's JITTER_RATE).
JITTER_RATE = 0.3


def random_scale(xy: np.ndarray, rng: np.random.Generator, rate: float = SCALE_RATE) -> np.ndarray:
    """(N, 2) x, y multiplied by one factor drawn uniformly from [1 - rate, 1 + rate]."""
    return xy * rng.uniform(1.0 - rate, 1.0 + rate)


def global_rotation(xy: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(N, 2) x, y rotated about z by an angle drawn uniformly from [0, 360) degrees."""
    angle = np.deg2rad(rng.random() * 360.0)
    cos, sin = np.cos(angle), np.sin(angle)
    return xy @ np.array([[cos, sin], [-sin, cos]])


def random_jitter(
    xy: np.ndarray, rng: np.random.Generator, rate: float = JITTER_RATE
) -> np.ndarray:
    """(N, 2) x, y shifted by one offset per scan from N(0, rate) per axis, clipped to +-rate."""
    return xy + np.clip(rng.normal(0.0, rate, 2), -rate, rate)


def random_flip(xy: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(N, 2) x, y with x negated, y negated, both or neither (one of the four drawn uniformly)."""
    choice = int(rng.integers(4))
    signs = ((1.0, 1.0), (-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0))[choice]
    return xy * np.asarray(signs)


def augment_points(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A copy of (N, 4) or (N, 5) points with the four augmentations applied to x and y, in the
    thesis's order.

    The arithmetic runs in float64 and the result keeps the input's dtype.
    """
    out = np.array(points, copy=True)
    xyz = out[:, :3]
    moved = np.isfinite(xyz).all(axis=1) & (xyz != 0).any(axis=1)
    xy = out[moved, :2].astype(np.float64)
    xy = random_scale(xy, rng)
    xy = global_rotation(xy, rng)
    xy = random_jitter(xy, rng)
    xy = random_flip(xy, rng)
    out[moved, :2] = xy
    return out
