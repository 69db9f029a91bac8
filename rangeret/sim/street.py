"""Generating a street scene: the road, sidewalks, parking, buildings, vegetation, poles and
vehicles laid out at random, each a labelled primitive of `rangeret.sim.scene`."""

from __future__ import annotations

import numpy as np

from rangeret.sim.scene import (
    BICYCLE,
    BICYCLIST,
    BUILDING,
    CAR,
    CURB_HEIGHT,
    FENCE,
    MARGIN,
    MOTORCYCLE,
    MOVING,
    OTHER_VEHICLE,
    PERSON,
    POLE,
    REMISSION,
    SIDEWALK,
    TRAFFIC_SIGN,
    TRUCK,
    TRUNK,
    UNLABELED,
    VEGETATION,
    Boxes,
    Cylinders,
    Ellipsoids,
    Scene,
)


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
        """An upright box of `length` x `width` centred on (x, y) from z0 to z1, turned by `yaw`."""
        rem = self.remission(label) if remission is None else remission
        self.boxes.append((x, y, length / 2, width / 2, yaw, z0, z1, label, rem, vx))

    def cylinder(self, x: float, y: float, r: float, z0: float, z1: float, label: int) -> None:
        """A vertical cylinder of radius `r` on the axis (x, y) from z0 to z1."""
        self.cylinders.append((x, y, r, z0, z1, label, self.remission(label)))

    def ellipsoid(
        self, x: float, y: float, z: float, rx: float, ry: float, rz: float, label: int
    ) -> None:
        """An axis-aligned ellipsoid centred on (x, y, z) with radii (rx, ry, rz)."""
        self.ellipsoids.append((x, y, z, rx, ry, rz, label, self.remission(label)))

    def build(self) -> tuple[Boxes, Cylinders, Ellipsoids]:
        """The collected primitives as arrays, one dataclass per kind."""
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
