"""The nuscenes profile and the tables layout: the devkit's facts, rows from the ring, and a
simulated tree read back as nuScenes lays it out.

The facts below are written out here from nuScenes-lidarseg's documentation and its devkit
(the 32 general classes with their indices, the challenge's 16 classes and the mapping between
them, the split sizes), independently of the profile file they check.
"""

from __future__ import annotations

import hashlib
import io
import json
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.cli.main import main
from rangeret.dataset.layout import discover
from rangeret.dataset.nuscenes_tables import TableError, find_version, read_tables
from rangeret.dataset.profiles import DatasetProfile, ProfileError, load_profile
from rangeret.dataset.projection import project_with
from rangeret.io.panoptic_labels import read_panoptic_npz, write_panoptic_npz
from rangeret.io.scans import ScanFormatError
from rangeret.sim import SensorConfig, simulate_scan
from rangeret.sim.dataset import sequence_scans
from rangeret.sim.nuscenes_tree import KEYFRAME_PERIOD, VERSION, simulate_nuscenes
from rangeret.sim.street import make_scene
from tests.support.devkit import run_devkit

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
#: nuScenes-panoptic's thing classes, and the general classes standing for them.
THINGS = {
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
}
THING_INDICES = [i for i, name in enumerate(GENERAL) if TO_CHALLENGE.get(name) in THINGS]
SCENES = {"scene-0061": 2, "scene-0103": 2, "scene-0916": 1}
SEED = 4


@pytest.fixture(scope="module")
def profile() -> DatasetProfile:
    return load_profile("nuscenes")


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory, profile: DatasetProfile) -> Path:
    root = tmp_path_factory.mktemp("nuscenes")
    sensor = SensorConfig.for_profile(profile, azimuth_steps=256)
    simulate_nuscenes(root, SCENES, sensor=sensor, seed=SEED, profile=profile)
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
            "panoptic",
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


def test_every_labelled_keyframe_has_panoptic_ground_truth(
    tree: Path, profile: DatasetProfile
) -> None:
    """Semantic parts are the lidarseg labels; thing points carry their object's number, one
    number per simulated object throughout its scene, numbered from 1; stuff points carry 0."""
    tables = read_tables(tree, VERSION)
    assert tables.has_panoptic
    records = json.loads((tree / VERSION / "panoptic.json").read_text())
    frames = [f for fs in tables.scenes.values() for f in fs]
    assert sorted(r["token"] for r in records) == sorted(f.token for f in frames)
    assert all(r["sample_data_token"] == r["token"] for r in records)
    assert len(list((tree / "panoptic" / VERSION).iterdir())) == len(frames)
    sensor = SensorConfig.for_profile(profile, azimuth_steps=256)
    for name, keyframes in tables.scenes.items():
        scans = sequence_scans(
            name, len(keyframes), sensor, SEED, profile=profile, period=KEYFRAME_PERIOD
        )
        numbers: dict[int, int] = {}
        for frame, (_, raw, _) in zip(keyframes, scans, strict=True):
            assert frame.panoptic_filename == f"panoptic/{VERSION}/{frame.token}_panoptic.npz"
            labels = np.fromfile(tree / frame.label_filename, np.uint8)
            assert ((raw & 0xFFFF) == labels).all()
            with np.load(tree / frame.panoptic_filename) as npz:
                assert npz.files == ["data"] and npz["data"].dtype == np.uint16
            values = read_panoptic_npz(tree / frame.panoptic_filename, len(labels))
            assert (values // 1000 == labels).all()
            instance = values % 1000
            thing = np.isin(labels, THING_INDICES)
            assert thing.any() and (instance[thing] > 0).all() and (instance[~thing] == 0).all()
            pairs = zip((raw[thing] >> 16).tolist(), instance[thing].tolist(), strict=True)
            for obj, number in set(pairs):
                assert numbers.setdefault(obj, number) == number, (name, obj)
            assert sorted(set(numbers.values())) == list(range(1, len(numbers) + 1))


def test_panoptic_files_go_with_the_labels(tmp_path: Path, profile: DatasetProfile) -> None:
    sensor = SensorConfig.for_profile(profile, azimuth_steps=64)
    some = tmp_path / "some"
    scenes = {"scene-0061": 1, "scene-0103": 2}
    simulate_nuscenes(some, scenes, labelled=["scene-0103"], sensor=sensor, profile=profile)
    tables = read_tables(some, VERSION)
    assert [f.panoptic_filename for f in tables.scenes["scene-0061"]] == [None]
    assert all(f.panoptic_filename for f in tables.scenes["scene-0103"])
    assert len(list((some / "panoptic" / VERSION).iterdir())) == 2
    for option in ("labelled", "panoptic"):
        root = tmp_path / option
        simulate_nuscenes(
            root, {"scene-0916": 1}, sensor=sensor, profile=profile, **{option: False}
        )
        tables = read_tables(root, VERSION)
        assert tables.has_lidarseg == (option == "panoptic") and not tables.has_panoptic
        assert not (root / VERSION / "panoptic.json").exists()
        assert not (root / "panoptic").exists()
        assert tables.scenes["scene-0916"][0].panoptic_filename is None


def test_a_broken_panoptic_record_is_named(tmp_path: Path, profile: DatasetProfile) -> None:
    sensor = SensorConfig.for_profile(profile, azimuth_steps=64)
    simulate_nuscenes(tmp_path, {"scene-0103": 2}, sensor=sensor, profile=profile)
    table = tmp_path / VERSION / "panoptic.json"
    records = json.loads(table.read_text())
    first = records[0]["token"]
    del records[1]["filename"]
    table.write_text(json.dumps(records))
    with pytest.raises(TableError, match=r"panoptic.json: record 1 has no str 'filename'"):
        read_tables(tmp_path, VERSION)
    records[1] = {**records[0], "token": first}
    table.write_text(json.dumps(records, indent=1))
    with pytest.raises(TableError, match=rf"record 1: sample_data {first} has a second panoptic"):
        read_tables(tmp_path, VERSION)
    table.write_text(json.dumps([records[0], 7]))
    with pytest.raises(TableError, match=r"panoptic.json: record 1 is not an object"):
        read_tables(tmp_path, VERSION)


def _npz(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def _npy_header(shape: tuple[int, ...]) -> bytes:
    buf = io.BytesIO()
    header = {"descr": "<u2", "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(buf, header)
    return buf.getvalue()


def test_a_panoptic_file_is_read_as_the_devkit_writes_it(tmp_path: Path) -> None:
    values = (np.arange(10, dtype=np.uint16) % 4) * 1000 + np.arange(10, dtype=np.uint16)
    np.savez_compressed(tmp_path / "devkit.npz", data=values)
    assert (read_panoptic_npz(tmp_path / "devkit.npz", 10) == values).all()
    write_panoptic_npz(tmp_path / "ours.npz", values)
    read = read_panoptic_npz(tmp_path / "ours.npz", 10)
    assert read.dtype == np.uint16 and (read == values).all()
    first = (tmp_path / "ours.npz").read_bytes()
    write_panoptic_npz(tmp_path / "ours.npz", values)
    assert (tmp_path / "ours.npz").read_bytes() == first
    with pytest.raises(ValueError, match=r"do not fit in uint16"):
        write_panoptic_npz(tmp_path / "big.npz", np.array([70_000]))


@pytest.mark.parametrize(
    ("case", "problem"),
    [
        ("no data", r"holds no array 'data' \(it holds labels\)"),
        ("int32", r"holds int32 values in 'data', not uint16"),
        ("object", r"holds object values in 'data', not uint16"),
        ("shape", r"holds an array 'data' of shape \(2, 5\), not one value per point"),
        ("length", r"holds 9 panoptic values but the sweep has 10 points"),
        ("cut", r"ends after 10 of the 20 bytes its header declares"),
        ("not zip", r"is not a panoptic npz file \(File is not a zip file\)"),
        ("large", r"is [0-9,]+ bytes, more than a panoptic file of 10 points takes"),
    ],
)
def test_a_panoptic_file_of_other_values_is_refused(
    tmp_path: Path, case: str, problem: str
) -> None:
    values = np.arange(10, dtype=np.uint16)
    path = tmp_path / "p.npz"
    if case == "no data":
        np.savez(path, labels=values)
    elif case == "int32":
        np.savez(path, data=values.astype(np.int32))
    elif case == "object":
        np.savez(path, data=np.array([1, None], dtype=object))
    elif case == "shape":
        np.savez(path, data=values.reshape(2, 5))
    elif case == "length":
        np.savez(path, data=values[:9])
    elif case == "cut":
        _npz(path, {"data.npy": _npy_header((10,)) + values[:5].tobytes()})
    elif case == "not zip":
        path.write_bytes(values.tobytes())
    else:
        np.savez(path, data=values, padding=np.zeros(70_000, np.uint8))
    with pytest.raises(ScanFormatError, match=problem) as refused:
        read_panoptic_npz(path, 10)
    message = str(refused.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    with pytest.raises(FileNotFoundError):
        read_panoptic_npz(tmp_path / "missing.npz", 10)


def test_a_panoptic_file_is_inflated_no_further_than_its_values(tmp_path: Path) -> None:
    """A member that inflates to 32 MB after a header of 10 values is read for those 10 alone."""
    member = _npy_header((10,)) + bytes(32 << 20)
    path = _npz(tmp_path / "bomb.npz", {"data.npy": member})
    assert path.stat().st_size < 64 << 10
    del member
    tracemalloc.start()
    try:
        values = read_panoptic_npz(path, 10)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert (values == 0).all() and peak < 1 << 20


@pytest.mark.slow
def test_the_devkit_reads_the_panoptic_ground_truth(tree: Path) -> None:
    loaded = run_devkit("load", "--dataroot", str(tree), "--version", VERSION)
    assert loaded["panoptic"] == loaded["lidarseg"] == sum(SCENES.values())
    first = loaded["first_panoptic"]
    assert first["dtype"] == "uint16" and first["semantic_is_lidarseg"] is True
    frames = [f for fs in read_tables(tree, VERSION).scenes.values() for f in fs]
    frame = next(f for f in frames if f.panoptic_filename == first["filename"])
    num_points = len(np.fromfile(tree / frame.label_filename, np.uint8))
    ours = read_panoptic_npz(tree / frame.panoptic_filename, num_points)
    assert first["points"] == num_points
    assert hashlib.sha256(ours.astype("<u2").tobytes()).hexdigest() == first["sha256"]
