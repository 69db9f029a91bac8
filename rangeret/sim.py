"""Synthetic SemanticKITTI data: a ray-casting simulator of a spinning LiDAR in street scenes.

A scene is a straight street along +x built from labelled primitives (upright boxes that may be
rotated about the vertical, vertical capped cylinders, ellipsoids) over a ground plane whose
label depends on where a ray lands (road, lane markings, parking, sidewalk, terrain, other
ground). A sensor modelled on the Velodyne HDL-64E (evenly spread beams, 360 degrees of azimuth)
drives along the street. A scan tests all its (ray, primitive) pairs at once, vectorised: the
pairs are those whose ray lies in the primitive's angular bounding window, so the work grows
with what the sensor sees rather than with rays x primitives. The nearest hit of each ray wins.

Labels use raw SemanticKITTI ids (instance ids in the high 16 bits for things), so the data goes
through the same readers, evaluator and pipeline as the real dataset. `simulate_dataset` writes a
SemanticKITTI tree, reproducible byte for byte from its seed.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from rangeret.atomic import atomic_write_bytes
from rangeret.io import write_labels, write_scan
from rangeret.layout import labels_dir, normalise_sequence, velodyne_dir

#: Seconds between two scans (the HDL-64E spins at 10 Hz).
SCAN_PERIOD = 0.1

UNLABELED, OUTLIER = 0, 1
CAR, BICYCLE, MOTORCYCLE, TRUCK, OTHER_VEHICLE = 10, 11, 15, 18, 20
PERSON, BICYCLIST = 30, 31
ROAD, PARKING, SIDEWALK, OTHER_GROUND = 40, 44, 48, 49
BUILDING, FENCE, LANE_MARKING = 50, 51, 60
VEGETATION, TRUNK, TERRAIN, POLE, TRAFFIC_SIGN = 70, 71, 72, 80, 81
MOVING = {CAR: 252, BICYCLIST: 253, TRUCK: 258, OTHER_VEHICLE: 259}

#: Mean remission of each material (raw id); moving classes use their static class's value.
REMISSION = {
    UNLABELED: 0.18,
    OUTLIER: 0.05,
    CAR: 0.2,
    BICYCLE: 0.25,
    MOTORCYCLE: 0.25,
    TRUCK: 0.3,
    OTHER_VEHICLE: 0.3,
    PERSON: 0.22,
    BICYCLIST: 0.25,
    ROAD: 0.2,
    PARKING: 0.25,
    SIDEWALK: 0.3,
    OTHER_GROUND: 0.27,
    BUILDING: 0.28,
    FENCE: 0.24,
    LANE_MARKING: 0.65,
    VEGETATION: 0.45,
    TRUNK: 0.34,
    TERRAIN: 0.4,
    POLE: 0.3,
    TRAFFIC_SIGN: 0.85,
}
for _static, _moving in MOVING.items():
    REMISSION[_moving] = REMISSION[_static]

#: Per-point remission noise, and the share of returns that are spurious (dust, multipath).
REMISSION_NOISE = 0.04
OUTLIER_RATE = 0.0005
#: Height of the raised sidewalk above the road.
CURB_HEIGHT = 0.12
#: Content reaches this far beyond both ends of the street, more than the sensor's range.
MARGIN = 90.0

_REMISSION_LUT = np.zeros(1 << 16, dtype=np.float64)
for _raw, _value in REMISSION.items():
    _REMISSION_LUT[_raw] = _value


@dataclass
class SensorConfig:
    """A spinning multi-beam LiDAR: beams evenly spread from `fov_up` to `fov_down` (degrees),
    `azimuth_steps` columns over 360 degrees, mounted `height` m above the ground, returns up to
    `max_range` m with gaussian range noise (m) and a share `dropout` of returns lost."""

    beams: int = 64
    azimuth_steps: int = 2048
    fov_up: float = 2.0
    fov_down: float = -24.8
    height: float = 1.73
    max_range: float = 80.0
    range_noise: float = 0.02
    dropout: float = 0.02

    def __post_init__(self) -> None:
        if self.beams < 1 or self.azimuth_steps < 1:
            raise ValueError(
                f"beams and azimuth_steps must be positive, got {self.beams} x {self.azimuth_steps}"
            )
        if not self.fov_down < self.fov_up or not -90 < self.fov_down <= self.fov_up < 90:
            raise ValueError(
                f"need -90 < fov_down < fov_up < 90 degrees, got {self.fov_down}, {self.fov_up}"
            )
        if self.height <= 0 or self.max_range <= 0:
            raise ValueError("height and max_range must be positive")
        if self.range_noise < 0 or not 0 <= self.dropout < 1:
            raise ValueError("range_noise must be >= 0 and dropout in [0, 1)")


@dataclass
class Boxes:
    """Upright boxes: centre (x, y), half extents along their own axes, yaw about the vertical,
    bottom and top z, full label (raw id | instance << 16), mean remission and x velocity (m/s)."""

    center: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    z: np.ndarray
    label: np.ndarray
    remission: np.ndarray
    vx: np.ndarray


@dataclass
class Cylinders:
    """Vertical capped cylinders: axis (x, y), radius, bottom and top z, label, remission."""

    center: np.ndarray
    radius: np.ndarray
    z: np.ndarray
    label: np.ndarray
    remission: np.ndarray


@dataclass
class Ellipsoids:
    """Axis-aligned ellipsoids: centre (x, y, z), radii (x, y, z), label, remission."""

    center: np.ndarray
    radii: np.ndarray
    label: np.ndarray
    remission: np.ndarray


@dataclass
class Scene:
    """A straight street along +x: the ground layout and the labelled primitives on it.

    The right side of the street is y < 0 (index 0 of per-side values), the left side y > 0.
    `sidewalk` holds each side's inner and outer |y|; `parking` and `other_ground` each side's
    sorted x intervals of parking strip and of paved ground beyond the sidewalk.
    The ego drives in the lane at `ego_y` at `ego_speed` m/s, so a scan at `pose_x` happens at
    time pose_x / ego_speed; moving boxes advance with that time and wrap around `extent`.
    """

    length: float
    extent: tuple[float, float]
    ego_y: float
    ego_speed: float
    lane_width: float
    lanes: int
    road_half: float
    parking_width: float
    sidewalk: np.ndarray
    parking: tuple[np.ndarray, np.ndarray]
    other_ground: tuple[np.ndarray, np.ndarray]
    dash_phase: float
    boxes: Boxes
    cylinders: Cylinders
    ellipsoids: Ellipsoids

    @property
    def num_primitives(self) -> int:
        """Number of boxes, cylinders and ellipsoids."""
        return len(self.boxes.yaw) + len(self.cylinders.radius) + len(self.ellipsoids.radii)


class _Builder:
    """Collects primitives while a scene is generated, and hands out instance ids."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.boxes: list[tuple[float, ...]] = []
        self.cylinders: list[tuple[float, ...]] = []
        self.ellipsoids: list[tuple[float, ...]] = []
        self.next_instance = 1

    def instance(self, raw: int) -> int:
        """A full label for a new thing of class `raw`."""
        label = raw | (self.next_instance << 16)
        self.next_instance += 1
        return label

    def remission(self, label: int, spread: float = 0.04) -> float:
        """A primitive's mean remission: its material's value, varied from object to object."""
        mean = REMISSION[label & 0xFFFF] + self.rng.normal(0.0, spread)
        return float(np.clip(mean, 0.02, 0.98))

    def box(
        self,
        x: float,
        y: float,
        length: float,
        width: float,
        z0: float,
        z1: float,
        label: int,
        yaw: float = 0.0,
        vx: float = 0.0,
        remission: float | None = None,
    ) -> None:
        rem = self.remission(label) if remission is None else remission
        self.boxes.append((x, y, length / 2, width / 2, yaw, z0, z1, label, rem, vx))

    def cylinder(self, x: float, y: float, r: float, z0: float, z1: float, label: int) -> None:
        self.cylinders.append((x, y, r, z0, z1, label, self.remission(label)))

    def ellipsoid(
        self, x: float, y: float, z: float, rx: float, ry: float, rz: float, label: int
    ) -> None:
        self.ellipsoids.append((x, y, z, rx, ry, rz, label, self.remission(label)))

    def build(self) -> tuple[Boxes, Cylinders, Ellipsoids]:
        b = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 10)
        c = np.asarray(self.cylinders, dtype=np.float64).reshape(-1, 7)
        e = np.asarray(self.ellipsoids, dtype=np.float64).reshape(-1, 8)
        boxes = Boxes(
            center=b[:, 0:2].copy(),
            half=b[:, 2:4].copy(),
            yaw=b[:, 4].copy(),
            z=b[:, 5:7].copy(),
            label=b[:, 7].astype(np.uint32),
            remission=b[:, 8].copy(),
            vx=b[:, 9].copy(),
        )
        cylinders = Cylinders(
            center=c[:, 0:2].copy(),
            radius=c[:, 2].copy(),
            z=c[:, 3:5].copy(),
            label=c[:, 5].astype(np.uint32),
            remission=c[:, 6].copy(),
        )
        ellipsoids = Ellipsoids(
            center=e[:, 0:3].copy(),
            radii=e[:, 3:6].copy(),
            label=e[:, 6].astype(np.uint32),
            remission=e[:, 7].copy(),
        )
        return boxes, cylinders, ellipsoids


def _intervals(
    rng: np.random.Generator,
    lo: float,
    hi: float,
    gap: tuple[float, float],
    run: tuple[float, float],
) -> np.ndarray:
    """Sorted disjoint (K, 2) intervals in [lo, hi]: gaps and runs of random lengths in turn."""
    out = []
    x = lo + rng.uniform(0.0, gap[1])
    while x < hi:
        end = min(x + rng.uniform(*run), hi)
        out.append((x, end))
        x = end + rng.uniform(*gap)
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def _vehicle(rng: np.random.Generator, kind: int) -> tuple[float, float, float]:
    """Length, width and height of a vehicle of raw class `kind`."""
    if kind == CAR:
        return rng.uniform(3.9, 4.9), rng.uniform(1.65, 1.9), rng.uniform(1.35, 1.65)
    if kind == TRUCK:
        return rng.uniform(7.0, 11.0), rng.uniform(2.3, 2.5), rng.uniform(3.0, 3.8)
    if kind == OTHER_VEHICLE:
        return rng.uniform(5.0, 7.5), rng.uniform(1.95, 2.2), rng.uniform(2.2, 2.8)
    return rng.uniform(1.9, 2.3), rng.uniform(0.7, 0.9), rng.uniform(1.1, 1.35)


def _place_vehicle(
    b: _Builder,
    kind: int,
    x: float,
    y: float,
    size: tuple[float, float, float],
    yaw: float = 0.0,
    vx: float = 0.0,
) -> None:
    """A vehicle as boxes sharing one instance: body and cabin for cars and vans, cab and cargo
    for trucks, a single box for motorcycles. `x` is the centre of its footprint."""
    length, width, height = size
    label = b.instance(MOVING.get(kind, kind) if vx else kind)
    rem = b.remission(label, spread=0.08)
    c, s = np.cos(yaw), np.sin(yaw)

    def part(offset: float, part_length: float, z0: float, z1: float, part_width: float) -> None:
        b.box(x + c * offset, y + s * offset, part_length, part_width, z0, z1, label, yaw, vx, rem)

    if kind == CAR:
        body = 0.55 * height
        part(0.0, length, 0.18, body, width)
        part(-0.08 * length, 0.55 * length, body, height, width - 0.12)
    elif kind == TRUCK:
        cab = 2.0
        part(length / 2 - cab / 2, cab, 0.3, height * 0.8, width)
        part(-cab / 2, length - cab - 0.2, 0.4, height, width)
    elif kind == OTHER_VEHICLE:
        part(0.0, length, 0.25, height, width)
    else:
        part(0.0, length, 0.0, height, width)


def make_scene(rng: np.random.Generator, length: float = 200.0) -> Scene:
    """A random urban street `length` m long (content reaches `MARGIN` m beyond both ends).

    Road with lane markings and parking strips, raised sidewalks with poles, signs, trees,
    pedestrians, bicycles and clutter, terrain with hedges, fences and other ground in front of
    and between buildings, parked vehicles and moving traffic.
    """
    if length <= 0:
        raise ValueError(f"length must be positive, got {length}")
    b = _Builder(rng)
    x_lo, x_hi = -MARGIN, length + MARGIN
    lanes = 1 if rng.random() < 0.6 else 2
    lane_width = rng.uniform(3.2, 3.7)
    road_half = lanes * lane_width
    parking_width = 2.4
    ego_speed = rng.uniform(8.0, 12.0)
    ego_y = -lane_width / 2
    sidewalk = np.empty((2, 2))
    parking: list[np.ndarray] = []
    other_ground: list[np.ndarray] = []

    # Moving traffic: one speed per lane so vehicles never run into each other.
    for side in (-1, 1):
        for lane in range(lanes):
            y = side * lane_width * (lane + 0.5)
            if side == -1 and lane == 0:
                x = rng.uniform(10.0, 40.0)
                for offset in (x, x + rng.uniform(20.0, 60.0), -rng.uniform(12.0, 50.0)):
                    if rng.random() < 0.6:
                        kind = CAR if rng.random() < 0.85 else OTHER_VEHICLE
                        size = _vehicle(rng, kind)
                        _place_vehicle(b, kind, offset, y, size, vx=ego_speed)
                continue
            speed = -side * rng.uniform(6.0, 15.0)
            x = x_lo + rng.uniform(0.0, 30.0)
            while True:
                r = rng.random()
                kind = CAR if r < 0.82 else OTHER_VEHICLE if r < 0.92 else TRUCK
                size = _vehicle(rng, kind)
                if x + size[0] > x_hi - 5.0:
                    break
                yaw = 0.0 if speed > 0 else np.pi
                _place_vehicle(b, kind, x + size[0] / 2, y, size, yaw, speed)
                x += size[0] + rng.uniform(10.0, 70.0)

    for index, side in enumerate((-1, 1)):
        verge = 0.0 if rng.random() < 0.5 else rng.uniform(1.2, 3.5)
        inner = road_half + parking_width + verge
        outer = inner + rng.uniform(1.8, 4.0)
        sidewalk[index] = inner, outer
        b.box(
            (x_lo + x_hi) / 2,
            side * (inner + outer) / 2,
            x_hi - x_lo,
            outer - inner,
            0.0,
            CURB_HEIGHT,
            SIDEWALK,
        )

        # Parked vehicles nose to tail in the parking strips.
        strips = _intervals(rng, x_lo, x_hi, gap=(5.0, 40.0), run=(12.0, 50.0))
        parking.append(strips)
        for start, end in strips:
            x = start + rng.uniform(0.2, 3.0)
            while True:
                r = rng.random()
                if r < 0.3:
                    x += rng.uniform(3.0, 8.0)
                    continue
                kind = (
                    CAR
                    if r < 0.85
                    else OTHER_VEHICLE
                    if r < 0.91
                    else TRUCK
                    if r < 0.95
                    else MOTORCYCLE
                )
                size = _vehicle(rng, kind)
                if x + size[0] > end:
                    break
                y = side * (road_half + parking_width / 2 + rng.uniform(-0.1, 0.1))
                yaw = rng.normal(0.0, 0.03) + (np.pi if rng.random() < 0.5 else 0.0)
                _place_vehicle(b, kind, x + size[0] / 2, y, size, yaw)
                x += size[0] + rng.uniform(0.6, 2.5)

        # Bicyclists riding at the road edge (one speed per side), or waiting at the kerb.
        speed = -side * rng.uniform(3.0, 7.0)
        for _ in range(rng.poisson(length / 80.0)):
            moving = rng.random() < 0.6
            label = b.instance(MOVING[BICYCLIST] if moving else BICYCLIST)
            y, z0 = (road_half - 0.45, 0.0) if moving else (inner + 0.5, CURB_HEIGHT)
            height = z0 + rng.uniform(1.6, 1.85)
            x = rng.uniform(x_lo, x_hi)
            b.box(x, side * y, rng.uniform(1.6, 1.8), 0.6, z0, height, label, vx=speed * moving)

        # Street furniture on the sidewalk.
        z0 = CURB_HEIGHT
        x = x_lo + rng.uniform(0.0, 30.0)
        while x < x_hi:
            height = rng.uniform(6.0, 9.0)
            y = side * (inner + 0.5)
            b.cylinder(x, y, rng.uniform(0.09, 0.14), z0, height, POLE)
            arm = rng.uniform(1.2, 2.8)
            b.box(x, y - side * arm / 2, 0.15, arm, height - 0.15, height, POLE)
            if rng.random() < 0.25:
                b.box(x - 0.1, y, 0.05, 0.6, 2.4, 3.0, TRAFFIC_SIGN)
            x += rng.uniform(25.0, 40.0)
        x = x_lo + rng.uniform(0.0, 40.0)
        while x < x_hi:
            height = rng.uniform(2.2, 3.0)
            y = side * (inner + 0.35)
            b.cylinder(x, y, rng.uniform(0.035, 0.05), z0, height, POLE)
            face = 0.06 * (1 if side < 0 else -1)
            size = rng.uniform(0.55, 0.8)
            b.box(x - face, y, 0.04, size, height - size, height + 0.02, TRAFFIC_SIGN)
            if rng.random() < 0.3:
                b.box(
                    x - face,
                    y,
                    0.04,
                    size,
                    height - 2 * size - 0.05,
                    height - size - 0.05,
                    TRAFFIC_SIGN,
                )
            x += rng.uniform(20.0, 60.0)
        if rng.random() < 0.8:
            x = x_lo + rng.uniform(0.0, 10.0)
            while x < x_hi:
                if verge:
                    _tree(b, x, side * (inner - verge / 2), 0.0)
                else:
                    _tree(b, x, side * (outer - rng.uniform(0.6, 1.0)), z0)
                x += rng.uniform(6.0, 14.0)
        if verge and rng.random() < 0.5:
            for x in _intervals(rng, x_lo, x_hi, gap=(5.0, 30.0), run=(3.0, 15.0)).mean(axis=1):
                rr = rng.uniform(0.4, min(1.0, verge / 2))
                b.ellipsoid(x, side * (inner - verge / 2), rr * 0.5, rr, rr, rr * 0.8, VEGETATION)
        for _ in range(rng.poisson(length / 20.0)):
            x, y = rng.uniform(x_lo, x_hi), side * rng.uniform(inner + 0.4, outer - 0.3)
            for _ in range(1 if rng.random() < 0.7 else rng.integers(2, 4)):
                b.cylinder(
                    x,
                    y,
                    rng.uniform(0.18, 0.28),
                    z0,
                    z0 + rng.uniform(1.5, 1.9),
                    b.instance(PERSON),
                )
                x += rng.uniform(0.6, 1.2)
        for _ in range(rng.poisson(length / 50.0)):
            x = rng.uniform(x_lo, x_hi)
            for _ in range(rng.integers(1, 4)):
                yaw = np.pi / 2 + rng.normal(0.0, 0.1)
                b.box(
                    x,
                    side * (outer - 0.9),
                    rng.uniform(1.6, 1.8),
                    0.45,
                    z0,
                    z0 + rng.uniform(0.95, 1.1),
                    b.instance(BICYCLE),
                    yaw,
                )
                x += rng.uniform(0.6, 0.9)
        for _ in range(rng.poisson(length / 30.0)):
            x, y = rng.uniform(x_lo, x_hi), side * rng.uniform(inner + 0.5, outer - 0.3)
            size = rng.uniform(0.5, 1.2)
            b.box(
                x,
                y,
                size,
                size * rng.uniform(0.6, 1.2),
                z0,
                z0 + rng.uniform(0.7, 1.5),
                UNLABELED,
                rng.uniform(0.0, np.pi),
            )

        other_ground.append(_buildings(b, side, outer, x_lo, x_hi))

    boxes, cylinders, ellipsoids = b.build()
    return Scene(
        length=float(length),
        extent=(x_lo, x_hi),
        ego_y=float(ego_y),
        ego_speed=float(ego_speed),
        lane_width=float(lane_width),
        lanes=lanes,
        road_half=float(road_half),
        parking_width=parking_width,
        sidewalk=sidewalk,
        parking=(parking[0], parking[1]),
        other_ground=(other_ground[0], other_ground[1]),
        dash_phase=float(rng.uniform(0.0, 9.0)),
        boxes=boxes,
        cylinders=cylinders,
        ellipsoids=ellipsoids,
    )


def _tree(b: _Builder, x: float, y: float, z0: float) -> None:
    """A trunk with an ellipsoidal crown on top."""
    rng = b.rng
    top = z0 + rng.uniform(1.8, 3.5)
    b.cylinder(x, y, rng.uniform(0.12, 0.3), z0, top, TRUNK)
    radius, rz = rng.uniform(1.2, 3.0), rng.uniform(1.2, 2.6)
    b.ellipsoid(x, y, top + 0.7 * rz, radius, radius * rng.uniform(0.85, 1.15), rz, VEGETATION)


def _buildings(b: _Builder, side: int, outer: float, x_lo: float, x_hi: float) -> np.ndarray:
    """Buildings set back behind the sidewalk, with terrain, hedges, fences, trees and paved
    yards (other ground) in front of and between them. Returns the other-ground intervals."""
    rng = b.rng
    paved = []
    x = x_lo + rng.uniform(-20.0, 0.0)
    while x < x_hi:
        width = rng.uniform(8.0, 30.0)
        setback = rng.uniform(0.5, 10.0) if rng.random() < 0.7 else rng.uniform(0.0, 0.5)
        depth = rng.uniform(8.0, 20.0)
        front = outer + setback
        yaw = rng.normal(0.0, 0.04) if rng.random() < 0.3 else 0.0
        b.box(
            x + width / 2,
            side * (front + depth / 2),
            width,
            depth,
            0.0,
            rng.uniform(5.0, 22.0),
            BUILDING,
            yaw,
        )
        if setback > 2.0:
            r = rng.random()
            y = side * (outer + rng.uniform(0.3, 0.8))
            if r < 0.3:
                b.box(
                    x + width / 2,
                    y,
                    width - 1.0,
                    rng.uniform(0.5, 1.0),
                    0.0,
                    rng.uniform(0.6, 1.6),
                    VEGETATION,
                )
            elif r < 0.55:
                b.box(
                    x + width / 2,
                    y,
                    width - 1.0,
                    rng.uniform(0.04, 0.1),
                    0.0,
                    rng.uniform(1.0, 2.0),
                    FENCE,
                )
            elif r < 0.75:
                for bx in np.arange(x + 1.0, x + width - 1.0, rng.uniform(2.0, 5.0)):
                    rr = rng.uniform(0.5, 1.2)
                    b.ellipsoid(bx, y + side * rr, rr * 0.6, rr, rr, rr * 0.8, VEGETATION)
            elif r < 0.85:
                paved.append((x, x + width))
        x += width
        if rng.random() < 0.4:
            gap = rng.uniform(3.0, 18.0)
            r = rng.random()
            if r < 0.5:
                b.box(
                    x + gap / 2,
                    side * (outer + setback),
                    gap,
                    rng.uniform(0.04, 0.1),
                    0.0,
                    rng.uniform(1.2, 2.2),
                    FENCE,
                )
            elif r < 0.8:
                _tree(b, x + gap / 2, side * (outer + setback + rng.uniform(2.0, 6.0)), 0.0)
            if rng.random() < 0.35:
                paved.append((x, x + gap))
            x += gap
        else:
            x += rng.uniform(0.0, 0.5)
    return np.asarray(paved, dtype=np.float64).reshape(-1, 2)


def _in_intervals(x: np.ndarray, intervals: np.ndarray) -> np.ndarray:
    """Whether each x lies in one of the sorted disjoint (K, 2) intervals."""
    if len(intervals) == 0:
        return np.zeros(x.shape, dtype=bool)
    k = np.searchsorted(intervals[:, 0], x, side="right") - 1
    return (k >= 0) & (x < intervals[np.maximum(k, 0), 1])


def ground_labels(scene: Scene, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Raw label of the ground at world points (x, y): road with its markings and parking
    strips, a grass verge (terrain) where the street has one, the sidewalk, then terrain or
    other ground in front of and between the buildings."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    ay = np.abs(y)
    left = y > 0
    out = np.full(x.shape, TERRAIN, dtype=np.uint32)
    beyond = ay >= np.where(left, scene.sidewalk[1, 1], scene.sidewalk[0, 1])
    paved = np.where(
        left, _in_intervals(x, scene.other_ground[1]), _in_intervals(x, scene.other_ground[0])
    )
    out[beyond & paved] = OTHER_GROUND
    inner = np.where(left, scene.sidewalk[1, 0], scene.sidewalk[0, 0])
    out[(ay >= inner) & ~beyond] = SIDEWALK
    strip = ay < scene.road_half + scene.parking_width
    parked = np.where(left, _in_intervals(x, scene.parking[1]), _in_intervals(x, scene.parking[0]))
    out[strip] = np.where(parked[strip] & (ay[strip] >= scene.road_half), PARKING, ROAD)
    half_line = 0.075
    dashed = np.mod(x - scene.dash_phase, 9.0) < 3.0
    divider = np.abs(ay - scene.lane_width * np.round(ay / scene.lane_width)) < half_line
    divider &= (ay < scene.road_half - 1.0) & dashed
    edge = np.abs(ay - (scene.road_half - 0.2)) < half_line
    out[divider | edge] = LANE_MARKING
    return out


@lru_cache(maxsize=8)
def _ray_grid(
    beams: int, steps: int, fov_up: float, fov_down: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit ray directions (beams * steps, 3), beam-major, and the beam elevations and column
    azimuths (radians). Column j looks at azimuth pi - (j + 0.5) 2 pi / steps, so the
    projection's u = floor(0.5 (-azimuth / pi + 1) W) gives back column j when W = steps."""
    elev = np.radians(np.linspace(fov_up, fov_down, beams)) if beams > 1 else np.radians([fov_up])
    azim = np.pi - (np.arange(steps) + 0.5) * (2 * np.pi / steps)
    ce = np.cos(elev)[:, None]
    dirs = np.empty((beams, steps, 3))
    dirs[..., 0] = ce * np.cos(azim)[None, :]
    dirs[..., 1] = ce * np.sin(azim)[None, :]
    dirs[..., 2] = np.sin(elev)[:, None]
    dirs = dirs.reshape(-1, 3)
    for array in (elev, azim, dirs):
        array.flags.writeable = False
    return elev, azim, dirs


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


def simulate_scan(
    scene: Scene, pose_x: float, sensor: SensorConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """One scan of `scene` by `sensor` at (pose_x, scene.ego_y), facing +x.

    Returns float32 (N, 4) points (x, y, z, remission) in the sensor frame (the ground at
    z = -height) and uint32 (N,) labels (raw id | instance << 16). Rays that hit nothing within
    `max_range`, and a random share `dropout` of the others, give no point.
    """
    _, _, dirs = _ray_grid(sensor.beams, sensor.azimuth_steps, sensor.fov_up, sensor.fov_down)
    origin = np.array([pose_x, scene.ego_y, sensor.height])
    time = pose_x / scene.ego_speed

    # The ground plane z = 0 catches every downward ray; primitives may come nearer.
    with np.errstate(divide="ignore"):
        best = np.where(dirs[:, 2] < 0, -sensor.height / dirs[:, 2], np.inf)
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
    points[:, 3] = np.clip(remission[keep], 0.0, 1.0)
    return points, labels[keep]


def _sequence_seed(seed: int, name: str) -> np.random.SeedSequence:
    """The seed of one sequence: the dataset seed and the sequence's name."""
    return np.random.SeedSequence(seed, spawn_key=tuple(name.encode("utf-8")))


def _matrix_line(values: Iterable[float]) -> str:
    return " ".join(f"{v:.12e}" for v in values)


def simulate_dataset(
    root: str | os.PathLike[str],
    sequences: Mapping[str, int],
    labelled: Iterable[str] | bool = True,
    sensor: SensorConfig | None = None,
    seed: int = 0,
    progress: bool = False,
) -> int:
    """Write a simulated SemanticKITTI tree under `root` and return the number of scans written.

    `sequences` maps a sequence name to its number of scans. Each sequence gets its own street
    and writes `sequences/XX/velodyne/NNNNNN.bin`, `labels/NNNNNN.label` when it is labelled
    (`labelled`: True for all, False for none, or the names of the labelled ones), and
    `poses.txt`, `times.txt` and `calib.txt` (the LiDAR is the reference frame: `Tr` is the
    identity and the poses are the sensor's). The same seed writes the same bytes.
    """
    sensor = sensor or SensorConfig()
    counts = {normalise_sequence(name): int(n) for name, n in sequences.items()}
    if any(n < 0 for n in counts.values()):
        raise ValueError(f"numbers of scans must be >= 0, got {counts}")
    if isinstance(labelled, bool):
        with_labels = set(counts) if labelled else set()
    else:
        with_labels = {normalise_sequence(name) for name in labelled}
        unknown = sorted(with_labels - set(counts))
        if unknown:
            raise ValueError(f"labelled sequences {unknown} are not among the sequences")

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(counts.values()), unit="scan", desc="simulating")
    written = 0
    try:
        for name, n in counts.items():
            seeds = _sequence_seed(seed, name).spawn(n + 1)
            scene = make_scene(np.random.default_rng(seeds[0]), max(200.0, 1.25 * n))
            step = scene.ego_speed * SCAN_PERIOD
            seq_dir = velodyne_dir(root, name).parent
            seq_dir.mkdir(parents=True, exist_ok=True)
            poses, times = [], []
            for k in range(n):
                points, labels = simulate_scan(
                    scene, k * step, sensor, np.random.default_rng(seeds[k + 1])
                )
                write_scan(velodyne_dir(root, name) / f"{k:06d}.bin", points)
                if name in with_labels:
                    write_labels(labels_dir(root, name) / f"{k:06d}.label", labels)
                poses.append(_matrix_line([1, 0, 0, k * step, 0, 1, 0, 0, 0, 0, 1, 0]))
                times.append(f"{k * SCAN_PERIOD:.6e}")
                written += 1
                if bar is not None:
                    bar.update(1)
            identity = _matrix_line([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0])
            calib = [f"P{i}: {identity}" for i in range(4)] + [f"Tr: {identity}"]
            for file, lines in (("poses.txt", poses), ("times.txt", times), ("calib.txt", calib)):
                atomic_write_bytes(seq_dir / file, "".join(f"{x}\n" for x in lines).encode())
    finally:
        if bar is not None:
            bar.close()
    return written
