"""The nuscenes profile and the tables layout: the devkit's facts, rows from the ring, and a
simulated tree read back as nuScenes lays it out.

The facts below are written out here from nuScenes-lidarseg's documentation and its devkit
(the 32 general classes with their indices, the challenge's 16 classes and the mapping between
them, the split sizes), independently of the profile file they check.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rangeret.cli.main import main
from rangeret.dataset.layout import discover
from rangeret.dataset.nuscenes_tables import TableError, find_version, read_tables
from rangeret.dataset.profiles import DatasetProfile, ProfileError, load_profile
from rangeret.dataset.projection import project_with
from rangeret.sim import SensorConfig, simulate_scan
from rangeret.sim.nuscenes_tree import VERSION, simulate_nuscenes
from rangeret.sim.street import make_scene

GENERAL = [
    "noise",
    "animal",
    "human.pedestrian.adult",
    "human.pedestrian.child",
    "human.pedestrian.construction_worker",
    "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer",
    "human.pedestrian.stroller",
    "human.pedestrian.wheelchair",
    "movable_object.barrier",
    "movable_object.debris",
    "movable_object.pushable_pullable",
    "movable_object.trafficcone",
    "static_object.bicycle_rack",
    "vehicle.bicycle",
    "vehicle.bus.bendy",
    "vehicle.bus.rigid",
    "vehicle.car",
    "vehicle.construction",
    "vehicle.emergency.ambulance",
    "vehicle.emergency.police",
    "vehicle.motorcycle",
    "vehicle.trailer",
    "vehicle.truck",
    "flat.driveable_surface",
    "flat.other",
    "flat.sidewalk",
    "flat.terrain",
    "static.manmade",
    "static.other",
    "static.vegetation",
    "vehicle.ego",
]
CHALLENGE = [
    "ignore",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
]
TO_CHALLENGE = {
    "human.pedestrian.adult": "pedestrian",
    "human.pedestrian.child": "pedestrian",
    "human.pedestrian.police_officer": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian",
    "vehicle.car": "car",
    "vehicle.motorcycle": "motorcycle",
    "vehicle.bicycle": "bicycle",
    "vehicle.bus.bendy": "bus",
    "vehicle.bus.rigid": "bus",
    "vehicle.truck": "truck",
    "vehicle.construction": "construction_vehicle",
    "vehicle.trailer": "trailer",
    "movable_object.barrier": "barrier",
    "movable_object.trafficcone": "traffic_cone",
    "flat.driveable_surface": "driveable_surface",
    "flat.sidewalk": "sidewalk",
    "flat.terrain": "terrain",
    "flat.other": "other_flat",
    "static.manmade": "manmade",
    "static.vegetation": "vegetation",
}
SCENES = {"scene-0061": 2, "scene-0103": 2, "scene-0916": 1}


@pytest.fixture(scope="module")
def profile() -> DatasetProfile:
    return load_profile("nuscenes")


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory, profile: DatasetProfile) -> Path:
    root = tmp_path_factory.mktemp("nuscenes")
    sensor = SensorConfig.for_profile(profile, azimuth_steps=256)
    simulate_nuscenes(root, SCENES, sensor=sensor, seed=4, profile=profile)
    return root


def test_profile_holds_the_devkits_classes_and_mapping(profile: DatasetProfile) -> None:
    labels = profile.labels
    assert labels.class_names == tuple(CHALLENGE)
    assert [labels.ignored[c] for c in range(17)] == [True] + [False] * 16
    assert {i: labels.raw_names[i] for i in range(32)} == dict(enumerate(GENERAL))
    for index, name in enumerate(GENERAL):
        expected = CHALLENGE.index(TO_CHALLENGE.get(name, "ignore"))
        assert labels.raw_to_class[index] == expected, name
    assert {k: len(v) for k, v in labels.splits.items()} == {
        "train": 700,
        "val": 150,
        "test": 150,
        "mini_train": 8,
        "mini_val": 2,
    }
    assert labels.split("mini_val") == ("scene-0103", "scene-0916")
    every = labels.split("train") + labels.split("val") + labels.split("test")
    assert len(set(every)) == 1000
    assert set(labels.split("mini_train") + labels.split("mini_val")) <= set(every)
    p = profile.projection
    assert (p.height, p.width, p.row) == (32, 1024, "ring")
    assert profile.points.fields == ("x", "y", "z", "intensity", "ring")
    assert profile.benchmark.predictions == "class" and profile.benchmark.classes_from == 1
    assert profile.knn.votes_from == 1 and 1 <= profile.unprojected_class <= 16


def test_profile_show_round_trips_and_lists(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["profile", "show", "nuscenes"]) == 0
    path = tmp_path / "n.yaml"
    path.write_text(capsys.readouterr().out)
    assert load_profile(path) == load_profile("nuscenes")
    assert main(["profile", "list"]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("nuscenes")]
    assert line and "rows from ring" in line[0] and "17 classes" in line[0]


def test_a_benchmark_section_is_checked(tmp_path: Path, profile: DatasetProfile) -> None:
    data = profile.to_dict()
    data["benchmark"]["predictions"] = "labels"
    with pytest.raises(ProfileError, match=r"benchmark.predictions: must be one of raw, class"):
        DatasetProfile.from_dict(data, "p.yaml")
    data = profile.to_dict()
    data["benchmark"]["unprojected_class"] = 17
    with pytest.raises(ProfileError, match=r"unprojected_class"):
        DatasetProfile.from_dict(data, "p.yaml")
    data = profile.to_dict()
    data["layout"]["tables"] = "lyft"
    with pytest.raises(ProfileError, match=r"layout.tables: must be one of nuscenes"):
        DatasetProfile.from_dict(data, "p.yaml")


def test_ring_rows_are_upright(profile: DatasetProfile) -> None:
    """Ring 0 is the lowest beam: the ring rule and the pitch rule put a simulated sweep's
    points on the same rows, so the image is upright, row 0 the top beam."""
    sensor = SensorConfig.for_profile(profile, azimuth_steps=512)
    rng = np.random.default_rng(2)
    points, _, lasers = simulate_scan(make_scene(rng), 30.0, sensor, rng, lasers=True)
    from rangeret.sim import beam_values

    rings = beam_values(lasers, profile)
    cloud = np.column_stack([points, rings])
    by_ring = project_with(cloud, profile.projection)
    import dataclasses

    by_pitch = project_with(cloud, dataclasses.replace(profile.projection, row="pitch"))
    assert (by_ring.proj_y == by_pitch.proj_y).mean() > 0.99
    highest = points[:, 2] / np.linalg.norm(points[:, :3], axis=1)
    assert rings[np.argmax(highest)] == 31 and by_ring.proj_y[np.argmax(highest)] == 0
    assert rings[np.argmin(highest)] == 0 and by_ring.proj_y[np.argmin(highest)] == 31


def test_a_ring_off_the_image_is_named(profile: DatasetProfile) -> None:
    cloud = np.array([[5, 0, 0, 10, 3], [5, 1, 0, 10, 32]], np.float32)
    with pytest.raises(ValueError, match=r"ring outside the image's rows 0..31.*point index 1"):
        project_with(cloud, profile.projection)


def test_the_simulated_tree_is_nuscenes_layout(tree: Path, profile: DatasetProfile) -> None:
    names = sorted(p.name for p in (tree / VERSION).iterdir())
    assert names == sorted(
        f"{t}.json"
        for t in [
            "category",
            "attribute",
            "visibility",
            "instance",
            "sensor",
            "calibrated_sensor",
            "ego_pose",
            "log",
            "scene",
            "sample",
            "sample_data",
            "sample_annotation",
            "map",
            "lidarseg",
        ]
    )
    assert len(list((tree / "maps").glob("*.png"))) == 1
    tables = read_tables(tree, VERSION)
    assert list(tables.scenes) == list(SCENES)
    assert [len(f) for f in tables.scenes.values()] == list(SCENES.values())
    assert tables.categories == dict(enumerate(GENERAL))
    records = json.loads((tree / VERSION / "lidarseg.json").read_text())
    assert {r["token"] for r in records} == {f.token for fs in tables.scenes.values() for f in fs}
    for frames in tables.scenes.values():
        for frame in frames:
            assert frame.filename.startswith("samples/LIDAR_TOP/")
            assert frame.filename.endswith(".pcd.bin")
            points = np.fromfile(tree / frame.filename, np.float32).reshape(-1, 5)
            labels = np.fromfile(tree / frame.label_filename, np.uint8)
            assert frame.label_filename == f"lidarseg/{VERSION}/{frame.token}_lidarseg.bin"
            assert len(labels) == len(points) > 1000
            assert labels.max() <= 31 and points[:, 4].min() >= 0 and points[:, 4].max() <= 31
            assert points[:, 3].max() > 1.0  # 8-bit intensity, not a 0..1 remission


def test_discover_names_files_and_splits(tree: Path, profile: DatasetProfile) -> None:
    found = discover(tree, ["scene-0103", "scene-0061"], with_labels=True, layout=profile.layout)
    assert found.problems == []
    assert [e.sequence for e in found.scans] == ["scene-0103"] * 2 + ["scene-0061"] * 2
    first = found.scans[0]
    assert first.prediction == f"lidarseg/mini_val/{first.name}_lidarseg.bin"
    assert found.scans[2].prediction.startswith("lidarseg/mini_train/")
    chosen = discover(tree, ["scene-0103"], layout=profile.layout, split="val").scans[0]
    assert chosen.prediction == f"lidarseg/val/{chosen.name}_lidarseg.bin"
    missing = discover(tree, ["scene-0655"], layout=profile.layout)
    assert missing.problems == [
        f"{tree.resolve() / VERSION / 'scene.json'} holds no scene scene-0655"
    ]


def test_version_is_found_or_asked_for(tmp_path: Path, tree: Path) -> None:
    assert find_version(tree) == VERSION
    with pytest.raises(TableError, match=r"holds no nuScenes version folder"):
        find_version(tmp_path)
    (tmp_path / "v1.0-mini").mkdir()
    (tmp_path / "v1.0-mini" / "scene.json").write_text("[]")
    (tmp_path / "v1.0-test").mkdir()
    (tmp_path / "v1.0-test" / "scene.json").write_text("[]")
    with pytest.raises(TableError, match=r"v1.0-mini, v1.0-test: choose one with --version"):
        find_version(tmp_path)
    assert find_version(tmp_path, "v1.0-test") == "v1.0-test"
    with pytest.raises(TableError, match=r"v1.0-trainval holds no nuScenes tables"):
        find_version(tmp_path, "v1.0-trainval")


def test_broken_tables_are_named(tmp_path: Path, profile: DatasetProfile) -> None:
    sensor = SensorConfig.for_profile(profile, azimuth_steps=64)
    simulate_nuscenes(tmp_path, {"scene-0103": 2}, sensor=sensor, profile=profile)
    scenes = tmp_path / VERSION / "scene.json"
    data = json.loads(scenes.read_text())
    data[0]["nbr_samples"] = 3
    scenes.write_text(json.dumps(data))
    with pytest.raises(TableError, match=r"scene.json: record 0 \(scene-0103\) says 3 samples"):
        read_tables(tmp_path, VERSION)
    data[0]["nbr_samples"] = 2
    scenes.write_text(json.dumps(data))
    categories = tmp_path / VERSION / "category.json"
    cats = json.loads(categories.read_text())
    cats[17]["name"], cats[23]["name"] = cats[23]["name"], cats[17]["name"]
    categories.write_text(json.dumps(cats))
    found = discover(tmp_path, ["scene-0103"], layout=profile.layout)
    assert any(
        "index 17 is 'vehicle.truck', but the profile's raw label 17 is 'vehicle.car'" in p
        for p in found.problems
    )
    (tmp_path / VERSION / "sample.json").write_text("{not json")
    with pytest.raises(TableError, match=r"sample.json is not a JSON table"):
        read_tables(tmp_path, VERSION)


def test_a_missing_sweep_or_label_is_a_problem(tmp_path: Path, profile: DatasetProfile) -> None:
    sensor = SensorConfig.for_profile(profile, azimuth_steps=64)
    simulate_nuscenes(tmp_path, {"scene-0916": 2}, sensor=sensor, profile=profile)
    frames = read_tables(tmp_path, VERSION).scenes["scene-0916"]
    (tmp_path / frames[0].filename).unlink()
    (tmp_path / frames[1].label_filename).unlink()
    found = discover(tmp_path, ["scene-0916"], with_labels=True, layout=profile.layout)
    assert len(found.problems) == 2
    assert "is missing (the sweep of sample" in found.problems[0]
    assert "has no ground truth" in found.problems[1]
