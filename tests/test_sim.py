"""Tests of the LiDAR simulator: the SemanticKITTI tree it writes and the plausibility of its scans."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from rangeret.io import read_labels, read_scan
from rangeret.labels import semantickitti
from rangeret.layout import labels_dir, velodyne_dir
from rangeret.projection import project
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
    written = simulate_dataset(tmp_path, {"00": 3, "11": 2}, labelled=["00"], sensor=SMALL, seed=1)
    assert written == 5
    assert sorted(p.name for p in (tmp_path / "sequences").iterdir()) == ["00", "11"]
    for seq, n in (("00", 3), ("11", 2)):
        names = [f"{k:06d}" for k in range(n)]
        assert sorted(p.name for p in velodyne_dir(tmp_path, seq).iterdir()) == [
            f"{s}.bin" for s in names
        ]
        seq_dir = tmp_path / "sequences" / seq
        for file in ("poses.txt", "times.txt"):
            assert len((seq_dir / file).read_text().splitlines()) == n
        calib = (seq_dir / "calib.txt").read_text().splitlines()
        assert [line.split(":")[0] for line in calib] == ["P0", "P1", "P2", "P3", "Tr"]
        for s in names:
            points = read_scan(velodyne_dir(tmp_path, seq) / f"{s}.bin")
            assert points.shape[1] == 4 and len(points) > 1000
            if seq == "00":
                labels = read_labels(labels_dir(tmp_path, seq) / f"{s}.label", len(points))
                assert set(np.unique(labels & 0xFFFF).tolist()) <= set(config.raw_to_class)
    assert not labels_dir(tmp_path, "11").exists()
    assert len(list(labels_dir(tmp_path, "00").iterdir())) == 3


@pytest.mark.parametrize("labelled", [True, False])
def test_dataset_all_or_no_labels(tmp_path: Path, labelled: bool) -> None:
    simulate_dataset(tmp_path, {"08": 1, "9": 1}, labelled=labelled, sensor=SMALL)
    for seq in ("08", "09"):
        assert velodyne_dir(tmp_path, seq).is_dir()
        assert labels_dir(tmp_path, seq).is_dir() == labelled


def test_dataset_is_deterministic(tmp_path: Path) -> None:
    runs = {}
    for name, seed in (("a", 7), ("b", 7), ("c", 8)):
        simulate_dataset(tmp_path / name, {"00": 2, "01": 2}, sensor=SMALL, seed=seed)
        runs[name] = tree_bytes(tmp_path / name)
    assert runs["a"] == runs["b"]
    scan_name = "sequences/00/velodyne/000000.bin"
    assert runs["a"][scan_name] != runs["c"][scan_name]
    assert runs["a"][scan_name] != runs["a"]["sequences/01/velodyne/000000.bin"]
    assert runs["a"][scan_name] != runs["a"]["sequences/00/velodyne/000001.bin"]


def test_dataset_rejects_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not among"):
        simulate_dataset(tmp_path, {"00": 1}, labelled=["01"], sensor=SMALL)
    with pytest.raises(ValueError, match=">= 0"):
        simulate_dataset(tmp_path, {"00": -1}, sensor=SMALL)
    with pytest.raises(ValueError):
        SensorConfig(fov_up=-30.0, fov_down=-25.0)
    with pytest.raises(ValueError):
        SensorConfig(dropout=1.0)


def test_dataset_progress(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert simulate_dataset(tmp_path, {"00": 2}, sensor=SMALL, progress=True) == 2
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
