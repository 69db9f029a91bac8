"""The sensor and its scans: a spinning multi-beam LiDAR cast against a scene.

The sensor is modelled on the Velodyne HDL-64E (evenly spread beams, 360 degrees of azimuth);
`SensorConfig.for_profile` gives the sensor of a dataset profile instead (one beam per image row,
as PandaSet's Pandar64 or SemanticPOSS's 40-beam sensor). A scan tests all its (ray, primitive) pairs at once, vectorised: the pairs are those whose ray
lies in the primitive's angular bounding window, so the work grows with what the sensor sees
rather than with rays x primitives. The nearest hit of each ray wins; range noise, dropout,
remission noise and spurious returns are added to the hits.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Literal, overload

import numpy as np

from rangeret.exceptions import InputError
from rangeret.sim.scene import (
    OUTLIER,
    REMISSION,
    Boxes,
    Cylinders,
    Ellipsoids,
    Scene,
    ground_labels,
)

if TYPE_CHECKING:
    from rangeret.dataset.profiles import DatasetProfile

#: Per-point remission noise, and the share of returns that are spurious (dust, multipath).
REMISSION_NOISE = 0.04
OUTLIER_RATE = 0.0005

# Mean remission by raw id, to look up the ground's materials by their labels.
_REMISSION_LUT = np.zeros(1 << 16, dtype=np.float64)
for _raw, _value in REMISSION.items():
    _REMISSION_LUT[_raw] = _value


class SimulationError(InputError, ValueError):
    """A simulation that cannot be run as asked: a sensor out of range or a profile it cannot fill."""


@dataclass
class SensorConfig:
    """A spinning multi-beam LiDAR: beams evenly spread from `fov_up` to `fov_down` (degrees), the
    top beam (laser id 0) first, or aimed at `elevations`; `azimuth_steps` columns over 360
    degrees, mounted `height` m above the ground and moved by `offset` (forward, left, up, in m)
    from there; returns up to `max_range` m with gaussian range noise (m) and a share `dropout` of
    returns lost."""

    beams: int = 64
    azimuth_steps: int = 2048
    fov_up: float = 2.0
    fov_down: float = -24.8
    height: float = 1.73
    max_range: float = 80.0
    range_noise: float = 0.02
    dropout: float = 0.02
    #: The reflectance written for a perfect reflector: 1 for remission, 255 for 8-bit intensity.
    reflectance_max: float = 1.0
    #: Elevation of each beam in degrees, top beam first (uneven beams); None: evenly spread.
    elevations: tuple[float, ...] | None = None
    #: Where the sensor sits from its mounting (forward, left, up, in m); points stay in its frame.
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.elevations is not None:
            self.elevations = tuple(float(e) for e in self.elevations)
            if any(not b < a for a, b in zip(self.elevations, self.elevations[1:], strict=False)):
                raise SimulationError("beam elevations must decrease strictly from the top beam")
            self.beams = len(self.elevations)
            self.fov_up, self.fov_down = self.elevations[0], self.elevations[-1]
        offset = [float(v) for v in self.offset]
        if len(offset) != 3 or not np.isfinite(offset).all():
            raise SimulationError(f"offset must be three finite numbers (m), got {offset}")
        self.offset = (offset[0], offset[1], offset[2])
        if not self.height + self.offset[2] > 0:
            raise SimulationError(
                f"the sensor must stay above the ground: a height of {self.height:g} m raised "
                f"by {self.offset[2]:g} m is not"
            )
        if self.beams < 1 or self.azimuth_steps < 1:
            raise SimulationError(
                f"beams and azimuth_steps must be positive, got {self.beams} x {self.azimuth_steps}"
            )
        if not self.fov_down < self.fov_up or not -90 < self.fov_down <= self.fov_up < 90:
            raise SimulationError(
                f"need -90 < fov_down < fov_up < 90 degrees, got {self.fov_down}, {self.fov_up}"
            )
        if self.height <= 0 or self.max_range <= 0:
            raise SimulationError("height and max_range must be positive")
        if self.range_noise < 0 or not 0 <= self.dropout < 1:
            raise SimulationError("range_noise must be >= 0 and dropout in [0, 1)")
        if not self.reflectance_max > 0:
            raise SimulationError(f"reflectance_max must be positive, got {self.reflectance_max}")

    @property
    def mount(self) -> np.ndarray:
        """The sensor's position relative to the point below its default mounting (m)."""
        dx, dy, dz = self.offset
        return np.array([dx, dy, self.height + dz])

    @classmethod
    def for_profile(
        cls,
        profile: DatasetProfile,
        azimuth_steps: int | None = None,
        offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> SensorConfig:
        """The sensor of a profile's range image: one beam per row, aimed at the row's centre so a
        pitch projection puts beam i on row i (or at `sensor.beam_angles`), 2 x width azimuth
        steps unless given, and the profile's `mount_height` and `max_range` where it has them."""
        p = profile.projection
        top, bottom = abs(p.fov_up), -abs(p.fov_down)
        half_row = (top - bottom) / p.height / 2
        defaults = cls()
        return cls(
            beams=p.height,
            azimuth_steps=2 * p.width if azimuth_steps is None else azimuth_steps,
            fov_up=top - half_row,
            fov_down=bottom + half_row,
            height=profile.mount_height or defaults.height,
            max_range=profile.max_range or defaults.max_range,
            reflectance_max=profile.reflectance_max,
            elevations=profile.beam_angles,
            offset=offset,
        )


def _elevations(sensor: SensorConfig) -> np.ndarray:
    """(beams,) elevation of each beam in degrees, top beam first."""
    if sensor.elevations is not None:
        return np.asarray(sensor.elevations)
    if sensor.beams > 1:
        return np.linspace(sensor.fov_up, sensor.fov_down, sensor.beams)
    return np.array([sensor.fov_up])


@lru_cache(maxsize=8)
def _ray_grid(elevations: tuple[float, ...], steps: int) -> np.ndarray:
    """Unit ray directions (beams * steps, 3), beam-major, read-only. Column j looks at azimuth
    pi - (j + 0.5) 2 pi / steps, so the projection's u = floor(0.5 (-azimuth / pi + 1) W) gives
    back column j when W = steps."""
    beams = len(elevations)
    elev = np.radians(np.asarray(elevations))
    azim = np.pi - (np.arange(steps) + 0.5) * (2 * np.pi / steps)
    ce = np.cos(elev)[:, None]
    dirs = np.empty((beams, steps, 3))
    dirs[..., 0] = ce * np.cos(azim)[None, :]
    dirs[..., 1] = ce * np.sin(azim)[None, :]
    dirs[..., 2] = np.sin(elev)[:, None]
    dirs = dirs.reshape(-1, 3)
    dirs.flags.writeable = False
    return dirs


def _candidate_pairs(
    lo: np.ndarray, hi: np.ndarray, sensor: SensorConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(ray, primitive) pairs worth testing: rays inside each primitive's angular window.

    `lo`, `hi` are (P, 3) corners of the primitives' axis-aligned bounds relative to the sensor.
    The window spans the beams between the lowest and highest elevation the bounds can show and
    the columns between the extreme azimuths of the footprint's corners; it is conservative.
    """
    beams, steps = sensor.beams, sensor.azimuth_steps
    nx = np.clip(0.0, lo[:, 0], hi[:, 0])
    ny = np.clip(0.0, lo[:, 1], hi[:, 1])
    dmin = np.hypot(nx, ny)
    dmax = np.hypot(np.maximum(-lo[:, 0], hi[:, 0]), np.maximum(-lo[:, 1], hi[:, 1]))
    zlo, zhi = lo[:, 2], hi[:, 2]
    e_hi = np.degrees(np.arctan2(zhi, np.where(zhi >= 0, dmin, dmax)))
    e_lo = np.degrees(np.arctan2(zlo, np.where(zlo >= 0, dmax, dmin)))
    if sensor.elevations is not None:
        # The beams from the first at or below e_hi to the last at or above e_lo.
        descending = -np.asarray(sensor.elevations)
        r0 = np.searchsorted(descending, -e_hi, side="left").astype(np.int64)
        r1 = np.searchsorted(descending, -e_lo, side="right").astype(np.int64) - 1
    else:
        step = (sensor.fov_up - sensor.fov_down) / (beams - 1) if beams > 1 else 1.0
        r0 = np.clip(np.floor((sensor.fov_up - e_hi) / step), 0, beams).astype(np.int64)
        r1 = np.clip(np.ceil((sensor.fov_up - e_lo) / step), -1, beams - 1).astype(np.int64)
    nrow = np.maximum(r1 - r0 + 1, 0)

    cx, cy = (lo[:, 0] + hi[:, 0]) / 2, (lo[:, 1] + hi[:, 1]) / 2
    centre = np.arctan2(cy, cx)
    corners = np.arctan2(
        np.stack([lo[:, 1], hi[:, 1], lo[:, 1], hi[:, 1]]),
        np.stack([lo[:, 0], lo[:, 0], hi[:, 0], hi[:, 0]]),
    )
    delta = np.mod(corners - centre + np.pi, 2 * np.pi) - np.pi
    a_hi = centre + delta.max(axis=0)
    a_lo = centre + delta.min(axis=0)
    scale = steps / (2 * np.pi)
    c0 = np.floor((np.pi - a_hi) * scale - 0.5).astype(np.int64)
    c1 = np.ceil((np.pi - a_lo) * scale - 0.5).astype(np.int64)
    inside = dmin <= 0.0
    c0 = np.where(inside, 0, c0)
    ncol = np.where(inside, steps, np.minimum(c1 - c0 + 1, steps))

    sizes = np.where(dmin <= sensor.max_range, nrow * ncol, 0)
    total = int(sizes.sum())
    prim = np.repeat(np.arange(len(sizes)), sizes)
    k = np.arange(total) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    width = ncol[prim]
    row = r0[prim] + k // width
    col = np.mod(c0[prim] + k % width, steps)
    return row * steps + col, prim


def _hit_boxes(
    o: np.ndarray, d: np.ndarray, boxes: Boxes, centre: np.ndarray, p: np.ndarray
) -> np.ndarray:
    """Distances along rays `d` (M, 3) from `o` to boxes `p` (slab test in each box's frame)."""
    c, s = np.cos(boxes.yaw)[p], np.sin(boxes.yaw)[p]
    ox, oy = o[0] - centre[p, 0], o[1] - centre[p, 1]
    dx, dy = d[:, 0], d[:, 1]
    near = np.full(len(p), -np.inf)
    far = np.full(len(p), np.inf)
    for origin, direction, half in (
        (c * ox + s * oy, c * dx + s * dy, boxes.half[p, 0]),
        (c * oy - s * ox, c * dy - s * dx, boxes.half[p, 1]),
    ):
        inv = 1.0 / np.where(np.abs(direction) < 1e-12, 1e-12, direction)
        t1, t2 = (-half - origin) * inv, (half - origin) * inv
        near = np.maximum(near, np.minimum(t1, t2))
        far = np.minimum(far, np.maximum(t1, t2))
    inv = 1.0 / np.where(np.abs(d[:, 2]) < 1e-12, 1e-12, d[:, 2])
    t1, t2 = (boxes.z[p, 0] - o[2]) * inv, (boxes.z[p, 1] - o[2]) * inv
    near = np.maximum(near, np.minimum(t1, t2))
    far = np.minimum(far, np.maximum(t1, t2))
    return np.where((near <= far) & (near > 0), near, np.inf)


def _hit_cylinders(o: np.ndarray, d: np.ndarray, cyl: Cylinders, p: np.ndarray) -> np.ndarray:
    """Distances along rays to vertical capped cylinders (side, then top and bottom caps)."""
    ox, oy = o[0] - cyl.center[p, 0], o[1] - cyl.center[p, 1]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    r2 = cyl.radius[p] ** 2
    z0, z1 = cyl.z[p, 0], cyl.z[p, 1]
    a = dx * dx + dy * dy
    half_b = ox * dx + oy * dy
    disc = half_b * half_b - a * (ox * ox + oy * oy - r2)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-half_b - np.sqrt(np.maximum(disc, 0.0))) / a
    z = o[2] + t * dz
    best = np.where((disc >= 0) & (t > 0) & (z >= z0) & (z <= z1), t, np.inf)
    inv = 1.0 / np.where(np.abs(dz) < 1e-12, 1e-12, dz)
    for zc in (z0, z1):
        tc = (zc - o[2]) * inv
        px, py = ox + tc * dx, oy + tc * dy
        best = np.where((tc > 0) & (px * px + py * py <= r2) & (tc < best), tc, best)
    return best


def _hit_ellipsoids(o: np.ndarray, d: np.ndarray, ell: Ellipsoids, p: np.ndarray) -> np.ndarray:
    """Distances along rays to ellipsoids (a unit sphere after scaling by the radii)."""
    radii = ell.radii[p]
    oc = (o[None, :] - ell.center[p]) / radii
    dc = d / radii
    a = np.einsum("ij,ij->i", dc, dc)
    half_b = np.einsum("ij,ij->i", oc, dc)
    disc = half_b * half_b - a * (np.einsum("ij,ij->i", oc, oc) - 1.0)
    t = (-half_b - np.sqrt(np.maximum(disc, 0.0))) / a
    return np.where((disc >= 0) & (t > 0), t, np.inf)


def _box_centres(scene: Scene, time: float) -> np.ndarray:
    """Box centres at `time`: moving boxes advance along x and wrap around the scene's extent."""
    boxes = scene.boxes
    centre = boxes.center.copy()
    moving = boxes.vx != 0
    if moving.any():
        x_lo, x_hi = scene.extent
        moved = centre[moving, 0] + boxes.vx[moving] * time
        centre[moving, 0] = x_lo + np.mod(moved - x_lo, x_hi - x_lo)
    return centre


@overload
def simulate_scan(
    scene: Scene,
    pose_x: float,
    sensor: SensorConfig,
    rng: np.random.Generator,
    *,
    lasers: Literal[False] = False,
) -> tuple[np.ndarray, np.ndarray]: ...


@overload
def simulate_scan(
    scene: Scene,
    pose_x: float,
    sensor: SensorConfig,
    rng: np.random.Generator,
    *,
    lasers: Literal[True],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


def simulate_scan(
    scene: Scene,
    pose_x: float,
    sensor: SensorConfig,
    rng: np.random.Generator,
    *,
    lasers: bool = False,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One scan of `scene` by `sensor` mounted at (pose_x, scene.ego_y) and moved by its
    `offset`, facing +x.

    Returns float32 (N, 4) points (x, y, z, remission) in the sensor frame (the ground at
    z = -(height + offset z)) and uint32 (N,) labels (raw id | instance << 16); with `lasers`,
    also each point's int64 beam index (laser id, 0 = the top beam). Rays that hit nothing
    within `max_range`, and a random share `dropout` of the others, give no point.
    """
    dirs = _ray_grid(tuple(_elevations(sensor).tolist()), sensor.azimuth_steps)
    origin = np.array([pose_x, scene.ego_y, 0.0]) + sensor.mount
    time = pose_x / scene.ego_speed

    # The ground plane z = 0 catches every downward ray; primitives may come nearer.
    with np.errstate(divide="ignore"):
        best = np.where(dirs[:, 2] < 0, -origin[2] / dirs[:, 2], np.inf)
    owner = np.where(np.isfinite(best), -1, -2)

    box_centre = _box_centres(scene, time)
    cyl, ell = scene.cylinders, scene.ellipsoids
    c, s = np.abs(np.cos(scene.boxes.yaw)), np.abs(np.sin(scene.boxes.yaw))
    hx, hy = scene.boxes.half[:, 0], scene.boxes.half[:, 1]
    ext = np.column_stack([c * hx + s * hy, s * hx + c * hy])
    bounds = [
        (
            np.column_stack([box_centre - ext, scene.boxes.z[:, 0]]),
            np.column_stack([box_centre + ext, scene.boxes.z[:, 1]]),
        ),
        (
            np.column_stack([cyl.center - cyl.radius[:, None], cyl.z[:, 0]]),
            np.column_stack([cyl.center + cyl.radius[:, None], cyl.z[:, 1]]),
        ),
        (ell.center - ell.radii, ell.center + ell.radii),
    ]
    rays, dists, owners = [], [], []
    offset = 0
    for kind, (lo, hi) in enumerate(bounds):
        ray, prim = _candidate_pairs(lo - origin, hi - origin, sensor)
        d = dirs[ray]
        if kind == 0:
            t = _hit_boxes(origin, d, scene.boxes, box_centre, prim)
        elif kind == 1:
            t = _hit_cylinders(origin, d, cyl, prim)
        else:
            t = _hit_ellipsoids(origin, d, ell, prim)
        hit = t < sensor.max_range
        rays.append(ray[hit])
        dists.append(t[hit])
        owners.append(prim[hit] + offset)
        offset += len(lo)
    ray, t, prim = np.concatenate(rays), np.concatenate(dists), np.concatenate(owners)
    np.minimum.at(best, ray, t)
    nearest = t == best[ray]
    owner[ray[nearest]] = prim[nearest]

    idx = np.flatnonzero(best <= sensor.max_range)
    idx = idx[rng.random(idx.size) >= sensor.dropout]
    dist, owner = best[idx], owner[idx]
    d = dirs[idx]

    labels = np.empty(idx.size, dtype=np.uint32)
    on_ground = owner == -1
    world = origin[None, :2] + d[on_ground, :2] * dist[on_ground, None]
    labels[on_ground] = ground_labels(scene, world[:, 0], world[:, 1])
    all_labels = np.concatenate([scene.boxes.label, cyl.label, ell.label])
    all_rem = np.concatenate([scene.boxes.remission, cyl.remission, ell.remission])
    labels[~on_ground] = all_labels[owner[~on_ground]]
    mean = np.empty(idx.size)
    mean[on_ground] = _REMISSION_LUT[labels[on_ground]]
    mean[~on_ground] = all_rem[owner[~on_ground]]
    remission = mean + rng.normal(0.0, REMISSION_NOISE, idx.size)

    dist = dist + rng.normal(0.0, sensor.range_noise, idx.size)
    spurious = rng.random(idx.size) < OUTLIER_RATE
    dist[spurious] *= rng.uniform(0.05, 0.9, int(spurious.sum()))
    labels[spurious] = OUTLIER
    remission[spurious] = rng.uniform(0.0, 0.1, int(spurious.sum()))

    keep = (dist > 0.5) & (dist <= sensor.max_range)
    points = np.empty((int(keep.sum()), 4), dtype=np.float32)
    points[:, :3] = d[keep] * dist[keep, None]
    points[:, 3] = np.clip(remission[keep], 0.0, 1.0) * np.float32(sensor.reflectance_max)
    if lasers:
        return points, labels[keep], idx[keep] // sensor.azimuth_steps
    return points, labels[keep]
