"""Instances from per-point classes (`rangeret.inference.instances`): connected components of the
range image's thing pixels, joined where the angle criterion of Bogoslavskyi and Stachniss (2016)
holds, with hidden, out-of-view and small pieces given to an instance of their class."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from rangeret.dataset.labels import semantickitti
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.projection import Projection, project
from rangeret.inference.instances import (
    ClusterSettings,
    ClusterSettingsError,
    InstanceInputError,
    pixel_positions,
    row_gaps,
    scan_instances,
)
from rangeret.io.scans import read_labels, read_scan
from tests.support.paths import data_path

CAR, PERSON, ROAD = 1, 6, 9
THINGS = {CAR, PERSON}
#: Angle between two rows of the constructed images (radians).
ROW_GAP = math.radians(0.4)


def scene(
    points: list[tuple[int, int, float, int]], height: int = 8, width: int = 32
) -> tuple[Projection, np.ndarray, np.ndarray]:
    """A projection, the points' xyz and classes from (row, column, range, class) per point; a
    row of -1 is a point outside the image. The closest point of a pixel wins, ties the first."""
    n = len(points)
    rows = np.array([p[0] for p in points], dtype=np.int64)
    cols = np.array([p[1] if p[0] >= 0 else -1 for p in points], dtype=np.int64)
    ranges = np.array([p[2] for p in points], dtype=np.float32)
    classes = np.array([p[3] for p in points], dtype=np.int64)
    proj_range = np.full((height, width), -1.0, dtype=np.float32)
    proj_idx = np.full((height, width), -1, dtype=np.int64)
    for i in np.lexsort((np.arange(n), ranges))[::-1]:
        if rows[i] >= 0:
            proj_range[rows[i], cols[i]] = ranges[i]
            proj_idx[rows[i], cols[i]] = i
    azimuth = (cols + 0.5) * 2 * math.pi / width
    elevation = -rows * ROW_GAP
    xyz = np.stack(
        [
            ranges * np.cos(elevation) * np.cos(azimuth),
            ranges * np.cos(elevation) * np.sin(azimuth),
            ranges * np.sin(elevation),
        ],
        axis=1,
    )
    projection = Projection(
        image=np.zeros((5, height, width), dtype=np.float32),
        mask=proj_idx >= 0,
        proj_range=proj_range,
        proj_idx=proj_idx,
        proj_x=cols,
        proj_y=np.where(rows >= 0, rows, -1),
        unproj_range=np.where(rows >= 0, ranges, 0).astype(np.float32),
    )
    return projection, xyz, classes


def block(rows: range, cols, distance: float, cls: int) -> list[tuple[int, int, float, int]]:
    """One point per pixel of rows x cols, all at one range."""
    return [(r, c, distance, cls) for r in rows for c in cols]


def instances(
    points: list[tuple[int, int, float, int]],
    settings: ClusterSettings | None = None,
    height: int = 8,
    width: int = 32,
) -> np.ndarray:
    projection, xyz, classes = scene(points, height, width)
    gaps = np.full(height - 1, ROW_GAP)
    return scan_instances(projection, xyz, classes, THINGS, gaps, settings or ClusterSettings())


def test_two_separate_objects_of_one_class_are_two_instances():
    a = block(range(2, 5), range(3, 7), 10.0, CAR)
    b = block(range(2, 5), range(15, 19), 10.0, CAR)
    ids = instances(a + b)
    assert ids.dtype == np.uint32
    assert set(ids[: len(a)]) == {1} and set(ids[len(a) :]) == {2}


def test_an_object_across_the_horizontal_wrap_around_is_one_instance():
    ids = instances(block(range(2, 5), [30, 31, 0, 1], 10.0, CAR))
    assert set(ids) == {1}


def test_the_angle_criterion_separates_depths_and_joins_one_surface():
    near = block(range(2, 5), range(3, 7), 10.0, CAR)
    far = block(range(2, 5), range(7, 11), 30.0, CAR)
    ids = instances(near + far)
    assert set(ids[: len(near)]) == {1} and set(ids[len(near) :]) == {2}
    same = block(range(2, 5), range(7, 11), 10.3, CAR)
    assert set(instances(near + same)) == {1}


@pytest.mark.parametrize("vertical", [False, True])
@pytest.mark.parametrize(("beta", "joined"), [(10.5, True), (9.5, False), (45.0, True)])
def test_two_pixels_join_exactly_when_beta_exceeds_the_threshold(vertical, beta, joined):
    """d2 from beta = atan2(d2 sin(alpha), d1 - d2 cos(alpha)), across a column or a row."""
    width, d1 = 32, 20.0
    alpha = ROW_GAP if vertical else 2 * math.pi / width
    t = math.tan(math.radians(beta))
    d2 = d1 * t / (math.sin(alpha) + t * math.cos(alpha))
    assert math.isclose(
        math.degrees(math.atan2(d2 * math.sin(alpha), d1 - d2 * math.cos(alpha))), beta
    )
    second = (4, 5) if vertical else (3, 6)
    ids = instances([(3, 5, d1, CAR), (*second, d2, CAR)], ClusterSettings(min_points=1))
    assert bool(ids[0] == ids[1]) is joined
    assert set(ids) == ({1} if joined else {1, 2})


def test_different_classes_never_share_an_instance_and_ids_run_over_the_scan():
    cars = block(range(2, 5), range(3, 7), 10.0, CAR)
    people = block(range(2, 5), range(7, 11), 10.0, PERSON)
    ids = instances(cars + people)
    assert set(ids[: len(cars)]) == {1} and set(ids[len(cars) :]) == {2}


def test_stuff_gets_zero_and_ids_are_one_to_k_in_the_order_of_first_points():
    road = block(range(5, 8), range(32), 8.0, ROAD)
    objects = [
        block(range(0, 3), range(20, 24), 15.0, PERSON),
        block(range(0, 3), range(2, 6), 12.0, CAR),
        block(range(0, 3), range(10, 14), 30.0, CAR),
    ]
    points = road + [p for o in objects for p in o]
    ids = instances(points)
    assert (ids[: len(road)] == 0).all()
    things = ids[len(road) :]
    assert (things > 0).all()
    assert np.array_equal(np.unique(things), np.arange(1, 4))
    start = len(road)
    for expected, o in enumerate(objects, start=1):
        assert set(ids[start : start + len(o)]) == {expected}
        start += len(o)


def test_hidden_points_take_the_nearest_in_range_pixel_of_their_class():
    near = block(range(2, 5), range(3, 7), 10.0, CAR)
    far = block(range(2, 5), range(7, 11), 30.0, CAR)
    hidden = [
        (3, 6, 29.0, CAR),  # behind the near car's pixel, at the far car's depth
        (3, 7, 29.9, CAR),  # behind the far car's own pixel
        (3, 5, 10.2, CAR),  # behind the near car, at its depth
    ]
    ids = instances(near + far + hidden)
    near_id, far_id = ids[0], ids[len(near)]
    assert near_id != far_id
    assert list(ids[-3:]) == [far_id, far_id, near_id]


def test_a_hidden_point_under_another_class_finds_its_class_in_the_window():
    car = block(range(2, 5), range(3, 7), 10.0, CAR)
    person = block(range(2, 5), range(7, 10), 5.0, PERSON)
    hidden = [(3, 9, 11.0, CAR)]  # behind the person, three columns from the car's edge
    ids = instances(car + person + hidden)
    assert ids[-1] == ids[0] != ids[len(car)]


def test_points_without_a_pixel_of_their_class_join_the_nearest_instance_of_it():
    left = block(range(2, 5), range(3, 7), 10.0, CAR)
    right = block(range(2, 5), range(20, 24), 10.0, CAR)
    person = block(range(2, 5), range(12, 15), 6.0, PERSON)
    lost = [
        (3, 13, 9.0, CAR),  # hidden by the person, no car within 3 columns
        (-1, 0, 0.0, CAR),  # outside the image, at the sensor
        (-1, 0, 0.0, ROAD),
    ]
    points = left + right + person + lost
    projection, xyz, classes = scene(points)
    xyz[-3] = xyz[len(left)]  # the hidden car point sits on the right-hand car
    ids = scan_instances(projection, xyz, classes, THINGS, np.full(7, ROW_GAP))
    assert ids[-3] == ids[len(left)] != ids[0]
    assert ids[-2] in (ids[0], ids[len(left)])
    assert ids[-1] == 0
    assert set(ids[len(left) + len(right) : -3]) == {3}


def test_points_of_a_class_without_instances_form_one_new_instance():
    car = block(range(2, 5), range(3, 7), 10.0, CAR)
    lost = [(-1, 0, 0.0, PERSON)] * 3
    projection, xyz, classes = scene(car + lost)
    xyz[-3:] = np.nan  # a point without a pixel may have no coordinates at all
    ids = scan_instances(projection, xyz, classes, THINGS, np.full(7, ROW_GAP))
    assert set(ids[: len(car)]) == {1} and set(ids[len(car) :]) == {2}


def test_small_clusters_merge_into_the_nearest_large_one_of_their_class():
    near = block(range(2, 5), range(3, 7), 10.0, CAR)  # 12 points
    far = block(range(2, 5), range(20, 24), 30.0, CAR)  # 12 points
    shard = block(range(2, 4), range(8, 10), 11.0, CAR)  # 4 points, apart from both
    lone = block(range(2, 4), range(26, 28), 11.0, PERSON)  # 4 points, the only person
    ids = instances(near + far + shard + lone)
    assert set(ids[24:28]) == {ids[0]}
    assert set(ids[28:]) == {3} and ids[len(near)] == 2
    assert np.array_equal(np.unique(ids), [1, 2, 3])
    kept = instances(near + far + shard + lone, ClusterSettings(min_points=4))
    assert len(set(kept[24:28]) - {kept[0], kept[12]}) == 1
    assert np.array_equal(np.unique(kept), [1, 2, 3, 4])


def test_a_small_cluster_counts_points_not_pixels():
    pixels = block(range(2, 4), range(3, 5), 10.0, CAR)  # 4 pixels
    behind = [(r, c, 10.5, CAR) for r, c, _, _ in pixels] * 2  # 8 more points on them
    big = block(range(2, 5), range(20, 24), 10.0, CAR)
    ids = instances(pixels + behind + big)
    assert len(set(ids[:12])) == 1 and ids[0] != ids[12]


def test_every_thing_point_gets_an_instance_on_a_random_scan():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(4000, 4)).astype(np.float32) * [20, 20, 2, 1]
    points[:5] = 0  # at the sensor: no pixel
    projection = project(points, 16, 128)
    classes = rng.integers(0, 5, size=len(points))
    things = np.array([False, True, True, False, True])
    gaps = np.full(15, math.radians(28 / 16))
    ids = scan_instances(projection, points, classes, things, gaps)
    assert ((ids > 0) == things[classes]).all()
    assert np.array_equal(np.unique(ids[ids > 0]), np.arange(1, ids.max() + 1))
    for i in np.unique(ids[ids > 0]):
        assert len(np.unique(classes[ids == i])) == 1
    for same in ({1, 2, 4}, [False, True, True, False, True], np.array([4, 2, 1])):
        assert np.array_equal(scan_instances(projection, points, classes, same, gaps), ids)


def test_without_coordinates_points_are_placed_by_their_pixel_and_range():
    near = block(range(2, 5), range(3, 7), 10.0, CAR)
    far = block(range(2, 5), range(20, 24), 30.0, CAR)
    shard = block(range(2, 4), range(8, 10), 11.0, CAR)
    lost = [(3, 13, 9.0, CAR), (-1, 0, 0.0, CAR)]
    projection, xyz, classes = scene(near + far + shard + lost)
    gaps = np.full(7, ROW_GAP)
    placed = pixel_positions(
        projection.proj_x, projection.proj_y, projection.unproj_range, 32, gaps
    )
    # The constructed points lie at their pixels' centres: the same shape, mirrored and turned.
    assert np.allclose(np.linalg.norm(placed, axis=1), np.linalg.norm(xyz, axis=1), atol=1e-5)
    assert np.allclose(placed[:, 2], xyz[:, 2], atol=1e-5)
    pairs = np.linalg.norm(placed[:, None] - placed[None], axis=2)
    assert np.allclose(pairs, np.linalg.norm(xyz[:, None] - xyz[None], axis=2), atol=1e-4)
    ids = scan_instances(projection, None, classes, THINGS, gaps)
    assert np.array_equal(ids, scan_instances(projection, xyz, classes, THINGS, gaps))
    assert set(ids[24:28]) == {ids[0]} and ids[-1] > 0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"angle": 0}, "angle"),
        ({"angle": 90}, "angle"),
        ({"angle": float("nan")}, "angle"),
        ({"angle": "10"}, "angle"),
        ({"angle": True}, "angle"),
        ({"min_points": 0}, "min_points"),
        ({"min_points": 2.5}, "min_points"),
        ({"min_points": True}, "min_points"),
    ],
)
def test_bad_settings_are_refused_naming_the_field(kwargs, field):
    with pytest.raises(ClusterSettingsError, match=rf"^{field} must"):
        ClusterSettings(**kwargs)


def test_arrays_that_do_not_fit_are_refused():
    projection, xyz, classes = scene(block(range(2, 5), range(3, 7), 10.0, CAR))
    gaps = np.full(7, ROW_GAP)
    with pytest.raises(InstanceInputError, match=r"^gaps"):
        scan_instances(projection, xyz, classes, THINGS, gaps[:-1])
    with pytest.raises(InstanceInputError, match=r"^classes"):
        scan_instances(projection, xyz, classes[:-1], THINGS, gaps)
    with pytest.raises(InstanceInputError, match=r"^classes must be below"):
        scan_instances(projection, xyz, classes, np.array([True]), gaps)
    with pytest.raises(InstanceInputError, match=r"^points_xyz"):
        scan_instances(projection, xyz[:, :2], classes, THINGS, gaps)


def test_row_gaps_follow_the_field_of_view_or_the_beams():
    profile = load_profile("semantickitti")
    assert np.allclose(row_gaps(profile), np.full(63, math.radians(28 / 64)))
    angles = tuple(2.0 - 0.5 * i - 0.01 * i * i for i in range(64))
    beams = replace(profile, beam_angles=angles)
    assert np.allclose(row_gaps(beams), np.radians(-np.diff(angles)))
    assert (row_gaps(beams) > 0).all()


def test_the_real_scan_gets_about_as_many_cars_as_its_ground_truth():
    """On the real scan with its ground-truth classes: every thing point has an instance, the
    car instances number within a factor 2 of the annotated ones, and the cars of 50 points or
    more (the panoptic benchmark's smallest scored size) are nearly all found at IoU > 0.5."""
    points = read_scan(data_path("semantickitti-scan", "000000.bin"))
    labels = read_labels(data_path("semantickitti-scan", "000000.label"), len(points))
    config = semantickitti()
    classes = config.to_class(labels & 0xFFFF)
    truth = labels >> 16
    things = np.isin(np.arange(config.num_classes), load_profile("semantickitti").things)
    projection = project(points)
    ids = scan_instances(
        projection, points, classes, things, row_gaps(load_profile("semantickitti"))
    )
    assert ((ids > 0) == things[classes]).all()
    car = classes == config.class_names.index("car")
    found, annotated = np.unique(ids[car]), np.unique(truth[car])
    assert annotated.size / 2 <= found.size <= 2 * annotated.size
    matched = 0
    large = [t for t in annotated if (car & (truth == t)).sum() >= 50]
    for t in large:
        mine = car & (truth == t)
        best = max(
            (mine & (ids == i)).sum() / (mine | (car & (ids == i))).sum()
            for i in np.unique(ids[mine])
        )
        matched += best > 0.5
    assert len(large) >= 4 and matched >= len(large) - 1
