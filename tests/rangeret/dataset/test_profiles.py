"""Dataset profile files and `rangeret profile`: list, show round trips, errors that name the file
and the field, and `profile stats` against a direct computation over the projected points."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from rangeret.cli.main import main
from rangeret.dataset.layout import discover
from rangeret.dataset.profile_stats import profile_stats
from rangeret.dataset.profiles import BUILTIN_PROFILES, DatasetProfile, ProfileError, load_profile
from rangeret.dataset.projection import project_with
from rangeret.io.scans import read_scan
from rangeret.sim import SensorConfig, simulate_dataset

SEQUENCES = {"1": 3, "2": 2}
#: The built-in profiles whose datasets are folders of sequences (nuScenes' are tables).
FOLDER_PROFILES = tuple(n for n in BUILTIN_PROFILES if load_profile(n).layout.folders is not None)


def profile_file(path: Path, base: str, changes: dict[str, Any]) -> Path:
    """The built-in `base` written to `path` with `changes` ("section.key": value) applied."""
    data = load_profile(base).to_dict()
    for dotted, value in changes.items():
        *sections, key = dotted.split(".")
        target = data
        for section in sections:
            target = target[section]
        target[key] = value
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def trees(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A small simulated tree of each built-in profile (coarse azimuth steps, to stay quick)."""
    root = tmp_path_factory.mktemp("trees")
    for name in FOLDER_PROFILES:
        profile = load_profile(name)
        sensor = SensorConfig.for_profile(profile, azimuth_steps=384)
        simulate_dataset(root / name, SEQUENCES, sensor=sensor, seed=3, profile=profile)
    return {name: root / name for name in FOLDER_PROFILES}


def direct_channels(root: Path, profile: DatasetProfile) -> tuple[np.ndarray, list[np.ndarray]]:
    """Raw (range, x, y, z, reflectance) of every pixel's winning point over the tree's scans, and
    each scan's points."""
    sequences = [profile.layout.normalise(s) for s in SEQUENCES]
    values, scans = [], []
    for entry in discover(root, sequences, layout=profile.layout).scans:
        points = read_scan(entry.scan_path, profile.points)
        proj = project_with(points, profile.projection)
        winners = proj.proj_idx[proj.mask]
        values.append(np.column_stack([proj.proj_range[proj.mask], points[winners, :4]]))
        scans.append(points)
    return np.concatenate(values).astype(np.float64), scans


# --- profile stats ------------------------------------------------------------------------------


def test_stats_equal_a_direct_computation(trees: dict[str, Path], tmp_path: Path) -> None:
    # 128 columns for about 384 rays a turn: most pixels have several points, the closest wins.
    path = profile_file(
        tmp_path / "narrow.yaml",
        "semantickitti",
        {"name": "narrow", "sensor.width": 128, "sensor.fov_up": 1.25, "sensor.fov_down": -20.2},
    )
    profile = load_profile(path)
    stats = profile_stats(trees["semantickitti"], ["01", "02"], profile)
    values, scans = direct_channels(trees["semantickitti"], profile)

    np.testing.assert_allclose(stats.means, values.mean(axis=0), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(stats.stds, values.std(axis=0), rtol=1e-12, atol=1e-13)
    points = sum(len(s) for s in scans)
    assert (stats.scans, stats.points, stats.pixels) == (5, points, len(values))
    assert 0.2 < stats.pixel_share < 0.9
    assert stats.fill == len(values) / (5 * 64 * 128)
    assert (stats.min_points, stats.max_points) == (
        min(len(s) for s in scans),
        max(len(s) for s in scans),
    )
    pitch = np.concatenate(
        [np.degrees(np.arcsin(s[:, 2] / np.linalg.norm(s[:, :3], axis=1))) for s in scans]
    )
    assert stats.above_fov == np.count_nonzero(pitch > 1.25) > 0
    assert stats.below_fov == np.count_nonzero(pitch < -20.2) > 0
    assert stats.pitch_range == pytest.approx((pitch.min(), pitch.max()), abs=1e-4)
    assert stats.laser_ids is None


def test_stats_of_laser_id_rows(trees: dict[str, Path]) -> None:
    profile = load_profile("pandaset")
    stats = profile_stats(trees["pandaset"], ["001", "002"], profile)
    values, scans = direct_channels(trees["pandaset"], profile)
    np.testing.assert_allclose(stats.means, values.mean(axis=0), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(stats.stds, values.std(axis=0), rtol=1e-12, atol=1e-13)
    lasers = np.concatenate([s[:, 4] for s in scans]).astype(int)
    assert stats.laser_ids == (lasers.min(), lasers.max()) == (0, 63)
    assert stats.distinct_laser_ids == len(np.unique(lasers))
    assert stats.above_fov is None and stats.outside_fov_share is None
    assert stats.channels == ("range", "x", "y", "z", "intensity")


def test_max_scans_spreads_over_the_selection(trees: dict[str, Path]) -> None:
    profile = load_profile("semantic-poss")
    every = profile_stats(trees["semantic-poss"], ["01", "02"], profile)
    two = profile_stats(trees["semantic-poss"], ["01", "02"], profile, max_scans=2)
    assert (every.scans, two.scans) == (5, 2)
    assert two.points < every.points
    with pytest.raises(ValueError, match="--max-scans"):
        profile_stats(trees["semantic-poss"], ["01"], profile, max_scans=0)


def test_stats_command_output_pastes_into_a_profile(
    trees: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "stats.json"
    args = ["--dataset", str(trees["semantickitti"]), "--sequences", "1", "2"]
    code = main(
        ["profile", "stats", "-q", *args, "--profile", "semantickitti", "--json", str(report)]
    )
    out = capsys.readouterr().out
    assert code == 0
    assert "5 scans" in out and "points per scan" in out and "outside the fov" in out
    numbers = json.loads(report.read_text())
    stats = profile_stats(trees["semantickitti"], ["01", "02"], load_profile("semantickitti"))
    assert numbers["means"] == list(stats.means) and numbers["stds"] == list(stats.stds)

    snippet = out.split("for the profile (sensor section):\n")[1].split("stats: ")[0]
    lines = [line for line in snippet.splitlines() if line.startswith("  ")]
    assert [line.split(":")[0] for line in lines] == ["  means", "  stds"]
    assert main(["profile", "show", "semantickitti"]) == 0
    shown = capsys.readouterr().out
    pasted, count = re.subn(
        r"  means:\n(  - .*\n)+  stds:\n(  - .*\n)+", "\n".join(lines) + "\n", shown
    )
    assert count == 1
    path = tmp_path / "my-sensor.yaml"
    path.write_text(pasted.replace("name: semantickitti", "name: my-sensor"))
    mine = load_profile(path)
    assert mine.projection.means == pytest.approx(stats.means, rel=1e-5)
    assert mine.projection.stds == pytest.approx(stats.stds, rel=1e-5)
    assert mine.labels == load_profile("semantickitti").labels


def test_stats_command_names_a_laser_id_off_the_image(
    trees: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = profile_file(tmp_path / "short.yaml", "pandaset", {"sensor.height": 32})
    args = ["--dataset", str(trees["pandaset"]), "--profile", str(path), "--sequences", "1"]
    assert main(["profile", "stats", "-q", *args]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1
    assert "001/velodyne/000000.bin" in err and "laser id" in err and "sensor.height is 32" in err


@pytest.mark.parametrize(
    ("where", "quiet"), [("before", True), ("after", True), ("nowhere", False)]
)
def test_quiet_before_or_after_the_action(where: str, quiet: bool) -> None:
    from rangeret.cli.main import build_parser

    options = ["--dataset", "d", "--profile", "pandaset", "--split", "train"]
    argv = {
        "before": ["profile", "-q", "stats", *options],
        "after": ["profile", "stats", *options, "-q"],
        "nowhere": ["profile", "stats", *options],
    }[where]
    args = build_parser("profile").parse_args(argv)
    assert (args.quiet, args.verbose) == (quiet, False)


# --- profile files ------------------------------------------------------------------------------


def test_profile_list_names_the_builtins(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["profile", "list"]) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert listed == list(BUILTIN_PROFILES)
    assert listed == ["semantickitti", "semantic-poss", "pandaset", "nuscenes"]


@pytest.mark.parametrize("name", BUILTIN_PROFILES)
def test_show_round_trips(name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["profile", "show", name]) == 0
    path = tmp_path / f"{name}.yaml"
    path.write_text(capsys.readouterr().out)
    assert load_profile(path) == load_profile(name)
    assert main(["profile", "show", str(path)]) == 0
    assert capsys.readouterr().out == path.read_text()


def _drop(data: dict[str, Any], dotted: str) -> None:
    *sections, key = dotted.split(".")
    for section in sections:
        data = data[section]
    del data[key]


@pytest.mark.parametrize(
    ("field", "edit"),
    [
        ("sensor.width", "missing"),
        ("splits", "missing"),
        ("sensor.colour", "extra"),
        ("colour", "extra"),
        ("sensor.height", -1),
        ("sensor.row", "azimuth"),
        ("sensor.stds", [1.0, 1.0, 0.0, 1.0, 1.0]),
        ("knn.votes_from", 99),
        ("points.fields", ["x", "y", "z"]),
        ("layout.id_digits", 0),
        ("labels.unlabeled_class", 20),
        ("sensor.fov_up", -2.0),
        ("sensor.fov_down", 5.0),
    ],
)
def test_a_wrong_field_is_named(field: str, edit: Any, tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    if edit == "missing":
        data = load_profile("semantickitti").to_dict()
        _drop(data, field)
        path.write_text(yaml.safe_dump(data, sort_keys=False))
    else:
        profile_file(path, "semantickitti", {field: "blue" if edit == "extra" else edit})
    with pytest.raises(ProfileError) as caught:
        load_profile(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: {field}: ")
    assert ("is missing" in message) == (edit == "missing")
    assert ("is not a profile field" in message) == (edit == "extra")


def test_a_wrong_list_item_is_named(tmp_path: Path) -> None:
    data = load_profile("pandaset").to_dict()
    data["labels"]["raw_labels"][3]["class"] = 15
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(
        ProfileError,
        match=r"labels\.raw_labels\[3\]\.class: raw id \d+ maps to unknown class 15 "
        r"\(must be a class 0\.\.14\)",
    ):
        load_profile(path)
    del data["labels"]["raw_labels"][3]["bgr"]
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(
        ProfileError, match=re.escape(f"{path}: labels.raw_labels[3].bgr: is missing")
    ):
        load_profile(path)


def test_a_misspelt_field_is_named_by_its_own_name(tmp_path: Path) -> None:
    data = load_profile("semantickitti").to_dict()
    data["sensor"]["widht"] = data["sensor"].pop("width")
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ProfileError, match=re.escape(f"{path}: sensor.widht: is not a profile")):
        load_profile(path)


def test_laser_id_rows_need_a_laser_id_field(tmp_path: Path) -> None:
    path = profile_file(tmp_path / "bad.yaml", "semantickitti", {"sensor.row": "laser_id"})
    with pytest.raises(
        ProfileError, match=re.escape(f"{path}: points.fields: must end with laser_id")
    ):
        load_profile(path)


@pytest.mark.parametrize("command", ["predict", "evaluate"])
def test_commands_refuse_a_bad_profile_in_one_line(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = profile_file(tmp_path / "bad.yaml", "semantickitti", {"knn.votes_from": 99})
    args = ["--dataset", str(tmp_path / "data"), "--split", "valid", "--profile", str(bad), "-q"]
    extra = ["--out", str(tmp_path / "out")] if command == "predict" else ["--predictions", "p"]
    assert main([command, *args, *extra]) == 1
    err = capsys.readouterr().err
    assert err.splitlines() == [
        f"rangeret {command}: error: {bad}: knn.votes_from: must be an integer 0..19, got 99"
    ]


def test_an_unknown_profile_names_the_builtins(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["profile", "show", "no-such-sensor"]) == 1
    err = capsys.readouterr().err
    assert "unknown profile 'no-such-sensor'" in err and "pandaset" in err


def test_the_semantickitti_profile_holds_the_bundled_label_configuration() -> None:
    """The profile's labels and `labels.semantickitti()` come from two files that must agree."""
    from rangeret.dataset.labels import semantickitti

    assert load_profile("semantickitti").labels == semantickitti()


# Hostile YAML ---------------------------------------------------------------------------------

_LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + "".join(
    f"{b}: &{b} [{', '.join(['*' + a] * 9)}]\n" for a, b in zip("abcdefgh", "bcdefghi", strict=True)
)


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        (_LAUGHS, "expands to more than 1,000,000 values through its aliases"),
        ("a: " + "[" * 5000 + "]" * 5000 + "\n", "nests deeper than 64 levels"),
        ("name: x\nsensor: " + "y" * 300_000 + "\n", None),  # a bad value quoted only in part
        ("a: [unclosed\n", "is not valid YAML"),
    ],
    ids=["billion-laughs", "deep-nesting", "huge-value", "not-yaml"],
)
def test_a_hostile_profile_file_is_one_short_line(tmp_path, capsys, text, problem):
    path = tmp_path / "hostile.yaml"
    path.write_text(text)
    assert main(["profile", "show", str(path)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and len(err) < 600 and str(path) in err, err[:600]
    if problem:
        assert problem in err, err


def test_a_hostile_label_configuration_is_one_short_line(tmp_path, capsys):
    path = tmp_path / "semantic-kitti.yaml"
    path.write_text(_LAUGHS)
    pred = tmp_path / "pred"
    pred.mkdir()
    argv = ["evaluate", "--dataset", str(tmp_path), "--predictions", str(pred), "--split", "valid"]
    assert main([*argv, "--label-config", str(path)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "expands to more than" in err, err[:600]


# Optional sensor fields -----------------------------------------------------------------------

#: Uneven beams of an 8-row profile with a +10 to -30 degree field of view.
BEAM_ANGLES = [10.0, 4.0, 1.0, 0.0, -1.0, -5.0, -12.0, -30.0]
SENSOR_8 = {"sensor.height": 8, "sensor.fov_up": 10.0, "sensor.fov_down": -30.0}


def test_beam_angles_max_range_and_mount_height_round_trip(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = profile_file(
        tmp_path / "uneven.yaml",
        "semantickitti",
        {
            **SENSOR_8,
            "sensor.beam_angles": BEAM_ANGLES,
            "sensor.max_range": 70.5,
            "sensor.mount_height": 1.9,
        },
    )
    profile = load_profile(path)
    assert profile.beam_angles == tuple(BEAM_ANGLES)
    assert (profile.max_range, profile.mount_height) == (70.5, 1.9)
    assert main(["profile", "show", str(path)]) == 0
    shown = capsys.readouterr().out
    assert yaml.safe_load(shown)["sensor"]["beam_angles"] == BEAM_ANGLES
    again = tmp_path / "again.yaml"
    again.write_text(shown)
    assert load_profile(again) == profile
    assert main(["profile", "show", str(again)]) == 0
    assert capsys.readouterr().out == shown
    plain = load_profile("semantickitti").to_dict()["sensor"]
    assert not {"beam_angles", "max_range", "mount_height"} & set(plain)


def test_another_height_drops_the_beam_angles(tmp_path: Path) -> None:
    path = profile_file(
        tmp_path / "uneven.yaml", "semantickitti", {**SENSOR_8, "sensor.beam_angles": BEAM_ANGLES}
    )
    profile = load_profile(path)
    assert profile.with_overrides(width=64).beam_angles == tuple(BEAM_ANGLES)
    assert profile.with_overrides(height=16).beam_angles is None
    assert DatasetProfile.from_dict(profile.with_overrides(height=16).to_dict()).beam_angles is None


@pytest.mark.parametrize(
    ("field", "value", "problem"),
    [
        ("beam_angles", BEAM_ANGLES[:7], "must be a list of 8 numbers"),
        ("beam_angles", [10.0, 4.0, 1.0, 1.0, -1.0, -5.0, -12.0, -30.0], "beam 3 (1) is not below"),
        (
            "beam_angles",
            [11.0, 4.0, 1.0, 0.0, -1.0, -5.0, -12.0, -30.0],
            "within the field of view",
        ),
        (
            "beam_angles",
            [10.0, 4.0, 1.0, 0.0, -1.0, -5.0, -12.0, -31.0],
            "within the field of view",
        ),
        ("max_range", 0, "must be positive, got 0"),
        ("max_range", "far", "must be a number, got 'far'"),
        ("mount_height", -1.5, "must be positive, got -1.5"),
    ],
)
def test_a_wrong_optional_sensor_field_is_named(
    field: str, value: Any, problem: str, tmp_path: Path
) -> None:
    path = profile_file(
        tmp_path / "bad.yaml", "semantickitti", {**SENSOR_8, f"sensor.{field}": value}
    )
    with pytest.raises(ProfileError) as caught:
        load_profile(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: sensor.{field}: ") and problem in message
    assert "\n" not in message


def test_thing_classes_and_the_panoptic_benchmark_of_each_builtin() -> None:
    kitti, nuscenes, pandaset = (load_profile(n) for n in ("semantickitti", "nuscenes", "pandaset"))
    assert kitti.thing_names == [
        "car",
        "bicycle",
        "motorcycle",
        "truck",
        "other-vehicle",
        "person",
        "bicyclist",
        "motorcyclist",
    ]
    assert len(nuscenes.things) == 10 and "traffic_cone" in nuscenes.thing_names
    assert (kitti.benchmark.panoptic, nuscenes.benchmark.panoptic) == (
        "semantickitti-panoptic",
        "nuscenes-panoptic",
    )
    assert pandaset.things == () and pandaset.benchmark.panoptic is None
    assert "names no thing classes" in str(pandaset.panoptic_refusal())
    assert kitti.panoptic_refusal() is None


@pytest.mark.parametrize(
    ("things", "problem"),
    [
        (["car", "dragon"], "'dragon' is not a class of the profile's labels"),
        (["car", "unlabeled"], "'unlabeled' is an ignored class"),
        (["car", "car"], "names a class twice"),
        ("car", "must be a list"),
    ],
)
def test_a_wrong_thing_class_is_named(things: Any, problem: str, tmp_path: Path) -> None:
    data = load_profile("semantickitti").to_dict()
    data["things"] = things
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ProfileError, match=re.escape(f"{path}: things: ")) as caught:
        load_profile(path)
    assert problem in str(caught.value)


def test_a_profile_names_its_panoptic_benchmark_or_none(tmp_path: Path) -> None:
    data = load_profile("semantickitti").to_dict()
    data["benchmark"]["panoptic"] = None
    path = tmp_path / "mine.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    assert load_profile(path).benchmark.panoptic is None
    del data["benchmark"]["panoptic"]
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    assert load_profile(path).benchmark.panoptic == "semantickitti-panoptic"
    del data["things"]
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    assert load_profile(path).things == ()
