"""Tests of the LiDAR simulator: the trees it writes (SemanticKITTI's and each profile's) and the
plausibility of its scans."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, discover, labels_dir, velodyne_dir
from rangeret.dataset.profiles import BUILTIN_PROFILES, DatasetProfile, load_profile
from rangeret.dataset.projection import project, project_with
from rangeret.io.scans import read_labels, read_scan
from rangeret.sim import (
    Boxes,
    Cylinders,
    Ellipsoids,
    Scene,
    SensorConfig,
    ground_labels,
    make_scene,
    simulate_dataset,
    simulate_scan,
)
from rangeret.sim.classes import CLASS_TABLES, raw_label_map

SMALL = SensorConfig(beams=32, azimuth_steps=256)
SENSOR_1024 = SensorConfig(azimuth_steps=1024)
GROUND_IDS = (40, 44, 60)


def tree_bytes(root: Path) -> dict[str, bytes]:
    """Every file under `root` by relative path, with its contents."""
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def empty_scene(scene: Scene) -> Scene:
    """`scene` with its ground layout but without any primitive."""
    return dataclasses.replace(
        scene,
        boxes=Boxes(
            center=np.empty((0, 2)),
            half=np.empty((0, 2)),
            yaw=np.empty(0),
            z=np.empty((0, 2)),
            label=np.empty(0, dtype=np.uint32),
            remission=np.empty(0),
            vx=np.empty(0),
        ),
        cylinders=Cylinders(
            center=np.empty((0, 2)),
            radius=np.empty(0),
            z=np.empty((0, 2)),
            label=np.empty(0, dtype=np.uint32),
            remission=np.empty(0),
        ),
        ellipsoids=Ellipsoids(
            center=np.empty((0, 3)),
            radii=np.empty((0, 3)),
            label=np.empty(0, dtype=np.uint32),
            remission=np.empty(0),
        ),
    )


@pytest.fixture(scope="module")
def scene() -> Scene:
    return make_scene(np.random.default_rng(3))


@pytest.fixture(scope="module")
def scan(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """One 64 x 1024 scan in the middle of the street."""
    return simulate_scan(scene, 80.0, SENSOR_1024, np.random.default_rng(4))


# --- the dataset tree --------------------------------------------------------------------------


def test_dataset_layout_and_files(tmp_path: Path) -> None:
    config = semantickitti()
    written = simulate_dataset(
        tmp_path,
        {"00": 3, "11": 2},
        labelled=["00"],
        sensor=SMALL,
        seed=1,
        profile=load_profile("semantickitti"),
    )
    assert written == 5
    assert sorted(p.name for p in (tmp_path / "sequences").iterdir()) == ["00", "11"]
    for seq, n in (("00", 3), ("11", 2)):
        names = [f"{k:06d}" for k in range(n)]
        assert sorted(
            p.name for p in velodyne_dir(tmp_path, seq, layout=KITTI_LAYOUT).iterdir()
        ) == [f"{s}.bin" for s in names]
        seq_dir = tmp_path / "sequences" / seq
        for file in ("poses.txt", "times.txt"):
            assert len((seq_dir / file).read_text().splitlines()) == n
        calib = (seq_dir / "calib.txt").read_text().splitlines()
        assert [line.split(":")[0] for line in calib] == ["P0", "P1", "P2", "P3", "Tr"]
        for s in names:
            points = read_scan(velodyne_dir(tmp_path, seq, layout=KITTI_LAYOUT) / f"{s}.bin")
            assert points.shape[1] == 4 and len(points) > 1000
            if seq == "00":
                labels = read_labels(
                    labels_dir(tmp_path, seq, layout=KITTI_LAYOUT) / f"{s}.label", len(points)
                )
                assert set(np.unique(labels & 0xFFFF).tolist()) <= set(config.raw_to_class)
    assert not labels_dir(tmp_path, "11", layout=KITTI_LAYOUT).exists()
    assert len(list(labels_dir(tmp_path, "00", layout=KITTI_LAYOUT).iterdir())) == 3


@pytest.mark.parametrize("labelled", [True, False])
def test_dataset_all_or_no_labels(tmp_path: Path, labelled: bool) -> None:
    simulate_dataset(
        tmp_path,
        {"08": 1, "9": 1},
        labelled=labelled,
        sensor=SMALL,
        profile=load_profile("semantickitti"),
    )
    for seq in ("08", "09"):
        assert velodyne_dir(tmp_path, seq, layout=KITTI_LAYOUT).is_dir()
        assert labels_dir(tmp_path, seq, layout=KITTI_LAYOUT).is_dir() == labelled


def test_dataset_is_deterministic(tmp_path: Path) -> None:
    runs = {}
    for name, seed in (("a", 7), ("b", 7), ("c", 8)):
        simulate_dataset(
            tmp_path / name,
            {"00": 2, "01": 2},
            sensor=SMALL,
            seed=seed,
            profile=load_profile("semantickitti"),
        )
        runs[name] = tree_bytes(tmp_path / name)
    assert runs["a"] == runs["b"]
    scan_name = "sequences/00/velodyne/000000.bin"
    assert runs["a"][scan_name] != runs["c"][scan_name]
    assert runs["a"][scan_name] != runs["a"]["sequences/01/velodyne/000000.bin"]
    assert runs["a"][scan_name] != runs["a"]["sequences/00/velodyne/000001.bin"]


def test_dataset_rejects_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not among"):
        simulate_dataset(
            tmp_path,
            {"00": 1},
            labelled=["01"],
            sensor=SMALL,
            profile=load_profile("semantickitti"),
        )
    with pytest.raises(ValueError, match=">= 0"):
        simulate_dataset(tmp_path, {"00": -1}, sensor=SMALL, profile=load_profile("semantickitti"))
    with pytest.raises(ValueError):
        SensorConfig(fov_up=-30.0, fov_down=-25.0)
    with pytest.raises(ValueError):
        SensorConfig(dropout=1.0)


def test_dataset_progress(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert (
        simulate_dataset(
            tmp_path, {"00": 2}, sensor=SMALL, progress=True, profile=load_profile("semantickitti")
        )
        == 2
    )
    assert "2/2" in capsys.readouterr().err


# --- the scans ---------------------------------------------------------------------------------


def test_scan_types_and_ranges(scan: tuple[np.ndarray, np.ndarray]) -> None:
    points, labels = scan
    assert points.dtype == np.float32 and points.shape[1] == 4
    assert labels.dtype == np.uint32 and labels.shape == (len(points),)
    assert 50_000 < len(points) <= 64 * 1024
    assert np.isfinite(points).all()
    depth = np.linalg.norm(points[:, :3], axis=1)
    assert depth.min() > 0 and depth.max() <= SENSOR_1024.max_range
    assert points[:, 3].min() >= 0 and points[:, 3].max() <= 1
    assert set(np.unique(labels & 0xFFFF).tolist()) <= set(semantickitti().raw_to_class)


def test_scan_elevations_in_field_of_view(scan: tuple[np.ndarray, np.ndarray]) -> None:
    points, _ = scan
    xyz = points[:, :3].astype(np.float64)
    pitch = np.degrees(np.arcsin(xyz[:, 2] / np.linalg.norm(xyz, axis=1)))
    assert pitch.min() >= SENSOR_1024.fov_down - 1e-3
    assert pitch.max() <= SENSOR_1024.fov_up + 1e-3


def test_ground_points_lie_on_the_ground(scan: tuple[np.ndarray, np.ndarray]) -> None:
    points, labels = scan
    ground = np.isin(labels & 0xFFFF, GROUND_IDS)
    assert ground.sum() > 10_000
    assert np.abs(points[ground, 2] + SENSOR_1024.height).max() < 0.1
    sidewalk = (labels & 0xFFFF) == 48
    assert np.median(points[sidewalk, 2]) > -SENSOR_1024.height


def test_noise_free_ground_is_exact(scene: Scene) -> None:
    sensor = dataclasses.replace(SENSOR_1024, range_noise=0.0, dropout=0.0)
    points, labels = simulate_scan(scene, 80.0, sensor, np.random.default_rng(0))
    ground = np.isin(labels & 0xFFFF, GROUND_IDS)
    assert np.abs(points[ground, 2] + sensor.height).max() < 1e-4
    world_x = points[ground, 0] + 80.0
    world_y = points[ground, 1] + scene.ego_y
    np.testing.assert_array_equal(ground_labels(scene, world_x, world_y), labels[ground])


def in_boxes(scene: Scene, world: np.ndarray, label: int, time: float) -> np.ndarray:
    """Whether world points lie (within 0.1 m) in a box labelled `label` at `time`."""
    boxes = scene.boxes
    x_lo, x_hi = scene.extent
    inside = np.zeros(len(world), dtype=bool)
    for i in np.flatnonzero(boxes.label == label):
        cx = boxes.center[i, 0] + boxes.vx[i] * time
        if boxes.vx[i]:
            cx = x_lo + np.mod(cx - x_lo, x_hi - x_lo)
        c, s = np.cos(boxes.yaw[i]), np.sin(boxes.yaw[i])
        dx, dy = world[:, 0] - cx, world[:, 1] - boxes.center[i, 1]
        inside |= (
            (np.abs(c * dx + s * dy) <= boxes.half[i, 0] + 0.1)
            & (np.abs(c * dy - s * dx) <= boxes.half[i, 1] + 0.1)
            & (world[:, 2] >= boxes.z[i, 0] - 0.1)
            & (world[:, 2] <= boxes.z[i, 1] + 0.1)
        )
    return inside


def to_world(scene: Scene, points: np.ndarray, pose_x: float, sensor: SensorConfig) -> np.ndarray:
    return points[:, :3].astype(np.float64) + np.array([pose_x, scene.ego_y, sensor.height])


def test_parked_car_points_lie_in_their_boxes(
    scene: Scene, scan: tuple[np.ndarray, np.ndarray]
) -> None:
    points, labels = scan
    parked = (labels & 0xFFFF) == 10
    assert parked.sum() > 100
    world = to_world(scene, points[parked], 80.0, SENSOR_1024)
    for label in np.unique(labels[parked]):
        mine = labels[parked] == label
        assert in_boxes(scene, world[mine], label, 80.0 / scene.ego_speed).mean() > 0.99


def test_scan_has_many_classes_and_instances(scan: tuple[np.ndarray, np.ndarray]) -> None:
    config = semantickitti()
    _, labels = scan
    classes = set(np.unique(config.to_class(labels)).tolist()) - {0}
    assert len(classes) >= 8, [config.class_names[c] for c in sorted(classes)]
    raw, instance = labels & 0xFFFF, labels >> 16
    things = np.isin(raw, (10, 11, 15, 18, 20, 30, 31, 252, 253, 258, 259))
    assert (instance[things] > 0).all() and (instance[~things] == 0).all()
    assert len(np.unique(instance[things])) >= 3


def test_projection_fills_the_range_image(scan: tuple[np.ndarray, np.ndarray]) -> None:
    points, _ = scan
    proj = project(points, 64, 1024, fov_up=3.0, fov_down=-25.0)
    assert 0.6 < proj.mask.mean() < 0.99


def test_rays_follow_the_projection_convention(scene: Scene) -> None:
    sensor = SensorConfig(
        beams=8, azimuth_steps=1024, fov_up=-5.0, fov_down=-20.0, range_noise=0.0, dropout=0.0
    )
    points, _ = simulate_scan(empty_scene(scene), 0.0, sensor, np.random.default_rng(0))
    assert len(points) == 8 * 1024
    proj = project(points, 64, 1024)
    assert proj.mask.sum() == 8 * 1024
    assert (np.bincount(proj.proj_x, minlength=1024) == 8).all()


def test_rays_without_a_hit_give_no_point(scene: Scene) -> None:
    sensor = SensorConfig(beams=4, azimuth_steps=64, fov_up=10.0, fov_down=1.0)
    points, labels = simulate_scan(empty_scene(scene), 0.0, sensor, np.random.default_rng(0))
    assert points.shape == (0, 4) and labels.shape == (0,)


def test_dropout_removes_returns(scene: Scene) -> None:
    counts = [
        len(
            simulate_scan(
                scene, 80.0, dataclasses.replace(SMALL, dropout=d), np.random.default_rng(0)
            )[0]
        )
        for d in (0.0, 0.5)
    ]
    assert 0.4 < counts[1] / counts[0] < 0.6


def test_ego_moves_forward_and_traffic_moves(scene: Scene) -> None:
    sensor = dataclasses.replace(SENSOR_1024, dropout=0.0)
    moving = scene.boxes.vx != 0
    assert moving.any() and (scene.boxes.label[moving] & 0xFFFF >= 252).all()
    centroids = {}
    for pose_x in (80.0, 80.0 + scene.ego_speed * 0.1):
        points, labels = simulate_scan(scene, pose_x, sensor, np.random.default_rng(0))
        world = to_world(scene, points, pose_x, sensor)
        raw = labels & 0xFFFF
        for label in np.unique(labels[(raw == 50) | (raw >= 252)]):
            mine = labels == label
            if label & 0xFFFF == 50:
                ok = in_boxes(scene, world[mine], label, pose_x / scene.ego_speed)
                assert ok.mean() > 0.99
            elif mine.sum() > 50:
                ok = in_boxes(scene, world[mine], label, pose_x / scene.ego_speed)
                assert ok.mean() > 0.99
                centroids.setdefault(int(label), []).append(world[mine, 0].mean())
    shifts = [abs(b - a) for a, b in (c for c in centroids.values() if len(c) == 2)]
    assert shifts and max(shifts) > 0.3


# --- dataset profiles --------------------------------------------------------------------------


def custom_profile(tmp_path: Path, base: str, **changes: object) -> DatasetProfile:
    """A profile file copied from the built-in `base`, named "campus", with `changes` applied
    to its top-level sections (a dict merges into the section)."""
    data = load_profile(base).to_dict()
    data["name"] = "campus"
    for key, value in changes.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    path = tmp_path / "campus.yaml"
    path.write_text(DatasetProfile.from_dict(data).to_yaml())
    return load_profile(path)


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_sensor_for_profile(name: str) -> None:
    p = load_profile(name).projection
    sensor = SensorConfig.for_profile(load_profile(name))
    assert (sensor.beams, sensor.azimuth_steps) == (p.height, 2 * p.width)
    row = (p.fov_up - p.fov_down) / p.height
    assert sensor.fov_up == pytest.approx(p.fov_up - row / 2)
    assert sensor.fov_down == pytest.approx(p.fov_down + row / 2)
    assert SensorConfig.for_profile(load_profile(name), azimuth_steps=300).azimuth_steps == 300


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_laser_ids_are_the_pitch_rows(scene: Scene, name: str) -> None:
    profile = load_profile(name)
    sensor = SensorConfig.for_profile(profile, azimuth_steps=512)
    points, labels, lasers = simulate_scan(
        scene, 80.0, sensor, np.random.default_rng(4), lasers=True
    )
    plain_points, plain_labels = simulate_scan(scene, 80.0, sensor, np.random.default_rng(4))
    np.testing.assert_array_equal(points, plain_points)
    np.testing.assert_array_equal(labels, plain_labels)
    assert lasers.shape == (len(points),)
    assert lasers.min() >= 0 and lasers.max() <= profile.projection.height - 1
    assert len(np.unique(lasers)) > profile.projection.height // 2
    pitch = project_with(points, dataclasses.replace(profile.projection, row="pitch"))
    assert (pitch.proj_y == lasers).mean() > 0.99


@pytest.mark.parametrize(
    "name", [n for n in BUILTIN_PROFILES if load_profile(n).layout.folders is not None]
)
def test_profile_dataset(tmp_path: Path, name: str) -> None:
    profile = load_profile(name)
    sensor = SensorConfig.for_profile(profile, azimuth_steps=256)
    assert simulate_dataset(tmp_path, {"5": 2}, sensor=sensor, seed=2, profile=profile) == 2
    seq = profile.layout.normalise(5)
    found = discover(tmp_path, [seq], with_labels=True, layout=profile.layout)
    assert found.problems == [] and [e.name for e in found.scans] == ["000000", "000001"]
    config = profile.labels
    classes: set[int] = set()
    for entry in found.scans:
        assert entry.scan_path.parent == velodyne_dir(tmp_path, seq, layout=profile.layout)
        assert entry.scan_path.stat().st_size % profile.points.point_bytes == 0
        points = read_scan(entry.scan_path, profile.points)
        assert points.shape[1] == profile.points.num_fields and len(points) > 1000
        assert entry.label_path is not None
        labels = read_labels(entry.label_path, len(points))
        assert set(np.unique(labels & 0xFFFF).tolist()) <= set(config.raw_to_class)
        classes |= set(np.unique(config.to_class(labels)).tolist()) - {config.unlabeled_class}
        proj = project_with(points, profile.projection)
        assert proj.valid.all()
        if profile.projection.row == "laser_id":
            np.testing.assert_array_equal(proj.proj_y, points[:, 4].astype(np.int64))
    assert len(classes) >= 8, [config.class_names[c] for c in sorted(classes)]


def test_builtin_profiles_landing_places(tmp_path: Path) -> None:
    for name, scan in (
        ("semantickitti", "sequences/08/velodyne/000000.bin"),
        ("semantic-poss", "dataset/sequences/08/velodyne/000000.bin"),
        ("pandaset", "008/velodyne/000000.bin"),
    ):
        sensor = SensorConfig(beams=4, azimuth_steps=64, fov_up=-5.0, fov_down=-20.0)
        simulate_dataset(tmp_path / name, {"8": 1}, sensor=sensor, profile=load_profile(name))
        assert (tmp_path / name / scan).is_file()


def test_semantickitti_profile_writes_the_same_bytes(tmp_path: Path) -> None:
    simulate_dataset(
        tmp_path / "a",
        {"00": 2},
        labelled=True,
        sensor=SMALL,
        seed=5,
        profile=load_profile("semantickitti"),
    )
    simulate_dataset(
        tmp_path / "b", {"00": 2}, sensor=SMALL, seed=5, profile=load_profile("semantickitti")
    )
    assert tree_bytes(tmp_path / "a") == tree_bytes(tmp_path / "b")
    ids = np.array(sorted(semantickitti().raw_to_class))
    np.testing.assert_array_equal(raw_label_map(load_profile("semantickitti"))[ids], ids)


def test_class_tables_are_classes_of_their_profiles() -> None:
    kitti = set(semantickitti().class_names)
    assert set(CLASS_TABLES) <= set(BUILTIN_PROFILES)
    for name, table in CLASS_TABLES.items():
        assert set(table) <= kitti
        assert set(table.values()) <= set(load_profile(name).labels.class_names)


def test_labels_of_other_profiles() -> None:
    poss, panda = (
        raw_label_map(load_profile("semantic-poss")),
        raw_label_map(load_profile("pandaset")),
    )
    # vegetation, terrain, moving car, bicyclist, lane marking, outlier
    assert poss[[70, 72, 252, 31, 60, 1]].tolist() == [9, 22, 7, 6, 22, 0]
    assert panda[[70, 72, 252, 31, 60, 1]].tolist() == [5, 6, 13, 0, 7, 0]


def test_custom_profile_maps_equal_class_names(tmp_path: Path) -> None:
    profile = custom_profile(tmp_path, "semantic-poss")
    lut = raw_label_map(profile)
    # car, pole, trunk keep their names; vegetation, terrain and bicycle have none in the file
    assert lut[[10, 80, 71, 70, 72, 11]].tolist() == [7, 13, 8, 0, 0, 0]
    sensor = SensorConfig.for_profile(profile, azimuth_steps=128)
    simulate_dataset(tmp_path / "data", {"02": 1}, sensor=sensor, profile=profile)
    labels = read_labels(
        labels_dir(tmp_path / "data", "02", layout=profile.layout) / "000000.label"
    )
    assert set(np.unique(labels & 0xFFFF).tolist()) <= {0, 4, 7, 8, 10, 13, 15, 17}


def test_sensor_defaults_to_the_profiles(tmp_path: Path) -> None:
    profile = custom_profile(
        tmp_path, "pandaset", sensor={"height": 8, "width": 64, "fov_up": 5.0, "fov_down": -20.0}
    )
    simulate_dataset(tmp_path / "data", {"1": 1}, profile=profile)
    points = read_scan(
        velodyne_dir(tmp_path / "data", "001", layout=profile.layout) / "000000.bin", profile.points
    )
    assert set(np.unique(points[:, 4]).tolist()) <= set(range(8))
    assert len(points) <= 8 * 128


def test_profile_the_simulator_cannot_fill(tmp_path: Path) -> None:
    timed = custom_profile(
        tmp_path, "semantickitti", points={"fields": ["x", "y", "z", "remission", "time"]}
    )
    with pytest.raises(ValueError, match="'time'"):
        simulate_dataset(tmp_path / "a", {"00": 1}, sensor=SMALL, profile=timed)
    with pytest.raises(ValueError, match="128 beams"):
        simulate_dataset(
            tmp_path / "b",
            {"00": 1},
            sensor=SensorConfig(beams=128, azimuth_steps=64),
            profile=load_profile("pandaset"),
        )
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
