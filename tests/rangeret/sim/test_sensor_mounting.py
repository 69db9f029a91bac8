"""Where the simulated sensor sits and how it is built: `simulate --sensor-offset`, a profile's
`mount_height` and `max_range`, and beams aimed at a profile's `beam_angles`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rangeret.cli.main import main
from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan
from rangeret.sim import (
    SensorConfig,
    ground_labels,
    make_scene,
    simulate_dataset,
    simulate_scan,
)
from rangeret.sim.raycast import SimulationError

ROAD = 40
#: Raw ids of the ground's materials in the simulated scenes.
GROUND = (40, 44, 48, 49, 60, 72)


def road_heights(root: Path, scan: str = "000000") -> np.ndarray:
    """z of the road points of one scan of sequence 00 (SemanticKITTI's layout)."""
    points = read_scan(root / "sequences" / "00" / "velodyne" / f"{scan}.bin", KITTI_RECORD)
    labels = read_labels(root / "sequences" / "00" / "labels" / f"{scan}.label", len(points))
    return points[(labels & 0xFFFF) == ROAD, 2]


def profile_with(tmp_path: Path, base: str, **sensor) -> DatasetProfile:
    """The built-in `base` with `sensor` fields set, read back from a file."""
    data = load_profile(base).to_dict()
    data["sensor"].update(sensor)
    path = tmp_path / f"{base}-edited.yaml"
    path.write_text(DatasetProfile.from_dict(data).to_yaml())
    return load_profile(path)


def test_a_higher_mounting_sees_the_ground_farther_down(tmp_path: Path) -> None:
    argv = ["simulate", "-q", "--sequences", "0:1", "--beams", "16", "--azimuth-steps", "256"]
    assert main([*argv, "--out", str(tmp_path / "low")]) == 0
    assert main([*argv, "--out", str(tmp_path / "high"), "--sensor-offset", "0", "0", "0.5"]) == 0
    low, high = road_heights(tmp_path / "low"), road_heights(tmp_path / "high")
    assert len(low) > 100 and len(high) > 100
    assert np.median(low) == pytest.approx(-1.73, abs=0.01)
    assert np.median(high) == pytest.approx(-2.23, abs=0.01)
    poses = (tmp_path / "high" / "sequences" / "00" / "poses.txt").read_text().split()
    assert [float(v) for v in poses[3:12:4]] == [0.0, 0.0, 0.5]


def test_an_offset_moves_the_sensor_in_the_scene() -> None:
    scene = make_scene(np.random.default_rng(2))
    offset = (1.0, -0.5, 0.25)
    sensor = SensorConfig(beams=16, azimuth_steps=256, range_noise=0.0, dropout=0.0, offset=offset)
    points, labels = simulate_scan(scene, 30.0, sensor, np.random.default_rng(0))
    ground = np.isin(labels & 0xFFFF, GROUND)
    assert ground.sum() > 500
    # Ground points lie 1.98 m below the sensor, and where their labels say in the scene.
    assert np.median(points[ground, 2]) == pytest.approx(-1.98, abs=1e-3)
    x, y, _ = points[ground].T.astype(np.float64)[:3]
    there = ground_labels(scene, 30.0 + offset[0] + x, scene.ego_y + offset[1] + y)
    assert (there == labels[ground]).mean() > 0.99
    unmoved = ground_labels(scene, 30.0 + x, scene.ego_y + y)
    assert (unmoved == labels[ground]).mean() < (there == labels[ground]).mean()
    with pytest.raises(SimulationError, match="must stay above the ground"):
        SensorConfig(offset=(0.0, 0.0, -2.0))


def test_a_profiles_mount_height_and_max_range_build_its_sensor(tmp_path: Path) -> None:
    profile = profile_with(tmp_path, "semantickitti", mount_height=2.5, max_range=30.0)
    sensor = SensorConfig.for_profile(profile, azimuth_steps=256)
    assert (sensor.height, sensor.max_range) == (2.5, 30.0)
    defaults = SensorConfig.for_profile(load_profile("semantickitti"))
    assert (defaults.height, defaults.max_range) == (1.73, 80.0)
    simulate_dataset(tmp_path / "tree", {"00": 1}, sensor=sensor, profile=profile)
    heights = road_heights(tmp_path / "tree")
    assert np.median(heights) == pytest.approx(-2.5, abs=0.01)
    points = read_scan(
        tmp_path / "tree" / "sequences" / "00" / "velodyne" / "000000.bin", KITTI_RECORD
    )
    assert np.linalg.norm(points[:, :3], axis=1).max() <= 30.1


def test_beams_aim_at_a_profiles_beam_angles(tmp_path: Path) -> None:
    angles = [4.0, 2.0, 1.0, 0.0, -2.0, -6.0, -12.0, -20.0]
    profile = profile_with(
        tmp_path, "pandaset", height=8, width=128, fov_up=5.0, fov_down=-25.0, beam_angles=angles
    )
    sensor = SensorConfig.for_profile(profile)
    assert sensor.elevations == tuple(angles) and sensor.beams == 8
    points, _, lasers = simulate_scan(
        make_scene(np.random.default_rng(5)), 40.0, sensor, np.random.default_rng(1), lasers=True
    )
    xyz = points[:, :3].astype(np.float64)
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    assert set(lasers.tolist()) == set(range(8))
    np.testing.assert_allclose(elevation, np.asarray(angles)[lasers], atol=1e-3)
