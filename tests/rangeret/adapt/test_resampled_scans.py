"""What `rangeret adapt` writes: source points moved by the offset with their labels, one per
target pixel, inside the target's field of view and range, each with its beam; and the
per-scan step's choices (the point nearest a pixel's centre wins, uneven beams, reflectance)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rangeret.adapt import adapt_scan, unmeasured_beams
from rangeret.cli.main import main
from rangeret.dataset.layout import discover, labels_dir, velodyne_dir
from rangeret.dataset.profiles import DatasetProfile, load_profile
from rangeret.dataset.projection import project, project_with
from rangeret.io.scans import read_labels, read_scan
from tests.rangeret.adapt.conftest import SOURCE_SEQUENCES, write_target

OFFSET = (0.4, -0.2, 0.3)
#: The label map of the mapped run: every SemanticKITTI id the scenes use, many to one.
VEHICLES, GROUND, OTHER = 13, 7, 0


@pytest.fixture(scope="module")
def ring_run(source_tree: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The source adapted to the 32-beam ring target, its sensor at OFFSET."""
    root = tmp_path_factory.mktemp("ring")
    target = write_target(root / "target.yaml", ring=True)
    out = root / "out"
    argv = ["adapt", "-q", "--dataset", str(source_tree), "--profile", "semantickitti"]
    argv += ["--to-profile", str(target), "--out", str(out), "--sequences", *SOURCE_SEQUENCES]
    assert main([*argv, "--sensor-offset", *map(str, OFFSET)]) == 0
    return {"out": out, "target": load_profile(target), "source": load_profile("semantickitti")}


def pairs(source_tree: Path, run: dict):
    """(source points, source labels, adapted points, adapted labels) of every scan."""
    source, target = run["source"], run["target"]
    for entry in discover(source_tree, list(SOURCE_SEQUENCES), layout=source.layout).scans:
        seq = target.layout.normalise(entry.sequence)
        points = read_scan(entry.scan_path, source.points)
        labels = read_labels(entry.label_path, len(points))
        scan = velodyne_dir(run["out"], seq, layout=target.layout) / f"{entry.name}.bin"
        adapted = read_scan(scan, target.points)
        label = labels_dir(run["out"], seq, layout=target.layout) / f"{entry.name}.label"
        yield points, labels, adapted, read_labels(label, len(adapted))


def matches(source_points: np.ndarray, adapted: np.ndarray) -> np.ndarray:
    """For each adapted point, the index of the source point it is, moved by OFFSET (the same
    three float32 values); -1 where none is."""
    moved = source_points[:, :3] - np.asarray(OFFSET, dtype=np.float32)
    index = {row.tobytes(): i for i, row in enumerate(moved)}
    return np.array([index.get(row.tobytes(), -1) for row in adapted[:, :3].copy()])


def test_every_adapted_point_is_a_source_point_moved_by_the_offset_with_its_label(
    source_tree: Path, ring_run: dict
) -> None:
    kept = 0
    for points, labels, adapted, adapted_labels in pairs(source_tree, ring_run):
        found = matches(points, adapted)
        assert (found >= 0).all()
        assert len(np.unique(found)) == len(found)
        assert np.all(np.diff(found) > 0), "points keep the source's order"
        np.testing.assert_array_equal(adapted_labels, labels[found])
        np.testing.assert_array_equal(
            adapted[:, 3], (points[found, 3].astype(np.float64) * 255).astype(np.float32)
        )
        assert len(adapted) > 2000
        kept += len(adapted)
    counts = json.loads((ring_run["out"] / "adapt.json").read_text())["counts"]
    assert counts["points_kept"] == kept and counts["scans"] == 3


def test_no_two_adapted_points_share_a_target_pixel(source_tree: Path, ring_run: dict) -> None:
    for *_, adapted, _ in pairs(source_tree, ring_run):
        proj = project(adapted[:, :4], 32, 256, 10.0, -30.0)
        pixels = proj.proj_y * 256 + proj.proj_x
        assert proj.valid.all() and len(np.unique(pixels)) == len(adapted)


def test_no_adapted_point_lies_outside_the_targets_field_of_view_or_range(
    source_tree: Path, ring_run: dict
) -> None:
    for *_, adapted, _ in pairs(source_tree, ring_run):
        xyz = adapted[:, :3].astype(np.float64)
        distance = np.linalg.norm(xyz, axis=1)
        elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
        assert distance.min() > 0 and distance.max() <= 40.0
        assert elevation.min() >= -30.0 and elevation.max() <= 10.0


def test_the_ring_field_is_the_beam_of_the_point(source_tree: Path, ring_run: dict) -> None:
    target = ring_run["target"]
    for *_, adapted, _ in pairs(source_tree, ring_run):
        rows = project(adapted[:, :4], 32, 256, 10.0, -30.0).proj_y
        np.testing.assert_array_equal(adapted[:, 4], (31 - rows).astype(np.float32))
        np.testing.assert_array_equal(project_with(adapted, target.projection).proj_y, rows)


def test_the_counts_add_up_and_name_the_beams_the_source_never_measured(
    source_tree: Path, ring_run: dict
) -> None:
    info = json.loads((ring_run["out"] / "adapt.json").read_text())
    counts = info["counts"]
    total = sum(len(points) for points, *_ in pairs(source_tree, ring_run))
    dropped = counts["dropped_fov"] + counts["dropped_range"] + counts["dropped_collisions"]
    assert counts["points_in"] == total == counts["points_kept"] + dropped
    assert counts["dropped_range"] > 0 and counts["dropped_collisions"] > 0
    # Beam centres 9.375 - 1.25 i degrees; SemanticKITTI's field of view is +3 to -25.
    assert info["unmeasured_beams"] == [0, 1, 2, 3, 4, 5, 28, 29, 30, 31]
    assert info["unmeasured_beams"] == unmeasured_beams(ring_run["source"], ring_run["target"])
    assert info["sensor_offset"] == list(OFFSET) and info["status"] == "finished"
    assert info["source_profile"]["name"] == "semantickitti"
    assert info["target_profile"]["name"] == "test-32" and info["label_map"] is None


def test_a_mapped_run_maps_each_label_and_keeps_its_instance(
    source_tree: Path, tmp_path: Path
) -> None:
    source = load_profile("semantickitti")
    entry = discover(source_tree, ["08"], layout=source.layout).scans[0]
    points = read_scan(entry.scan_path, source.points)
    labels = read_labels(entry.label_path, len(points))
    ids = np.unique(labels & 0xFFFF).tolist()
    mapping = {
        i: VEHICLES if 10 <= i < 30 or i >= 252 else GROUND if i in (40, 44, 48) else OTHER
        for i in ids
    }
    (tmp_path / "map.yaml").write_text("".join(f"{k}: {v}\n" for k, v in mapping.items()))
    out = tmp_path / "out"
    argv = ["adapt", "-q", "--dataset", str(source_tree), "--profile", "semantickitti"]
    argv += ["--to-profile", "pandaset", "--out", str(out), "--sequences", "8"]
    assert main([*argv, "--label-map", str(tmp_path / "map.yaml")]) == 0
    panda = load_profile("pandaset")
    adapted = read_scan(out / "008" / "velodyne" / "000000.bin", panda.points)
    written = read_labels(out / "008" / "labels" / "000000.label", len(adapted))
    moved = points[:, :3]
    index = {row.tobytes(): i for i, row in enumerate(moved)}
    found = np.array([index[row.tobytes()] for row in adapted[:, :3].copy()])
    lut = np.zeros(1 << 16, dtype=np.uint32)
    lut[list(mapping)] = list(mapping.values())
    source_labels = labels[found]
    np.testing.assert_array_equal(written & 0xFFFF, lut[source_labels & 0xFFFF])
    np.testing.assert_array_equal(written >> 16, source_labels >> 16)
    assert (written >> 16).any() and set(np.unique(written & 0xFFFF)) == {OTHER, GROUND, VEHICLES}
    np.testing.assert_array_equal(adapted[:, 4], project_with(adapted, panda.projection).proj_y)
    info = json.loads((out / "adapt.json").read_text())
    assert info["label_map"]["mapping"] == {str(k): v for k, v in sorted(mapping.items())}


# --- the per-scan step on points placed by hand -------------------------------------------------


def small_target(tmp_path: Path, **sensor) -> DatasetProfile:
    """A 4 x 8 target (+10 to -10 degrees: beam centres 7.5, 2.5, -2.5, -7.5), SemanticKITTI's
    labels, each point's laser id in its record."""
    data = load_profile("semantickitti").to_dict()
    data["sensor"].update(height=4, width=8, fov_up=10.0, fov_down=-10.0, **sensor)
    data["points"] = {"fields": ["x", "y", "z", "remission", "laser_id"]}
    path = tmp_path / "small.yaml"
    path.write_text(DatasetProfile.from_dict(data).to_yaml())
    return load_profile(path)


def direction(azimuth: float, elevation: float, distance: float) -> list[float]:
    """x, y, z of a point at `azimuth` and `elevation` (degrees), `distance` m away."""
    a, e = np.radians(azimuth), np.radians(elevation)
    return [
        distance * np.cos(e) * np.cos(a),
        distance * np.cos(e) * np.sin(a),
        distance * np.sin(e),
    ]


def test_the_point_nearest_the_pixels_centre_wins_then_the_lower_index(tmp_path: Path) -> None:
    # Column 3's centre looks at azimuth 22.5 degrees; row 1's beam at 2.5, row 3's at -7.5.
    points = np.array(
        [
            [*direction(32.0, 2.5, 5.0), 0.1],  # the nearest, but 9.5 degrees off the centre
            [*direction(24.0, 4.0, 20.0), 0.2],  # about 2 degrees off: wins row 1, column 3
            [*direction(22.5, -7.5, 8.0), 0.3],  # row 3's centre
            [0, 0, 0, 0.4],  # the same direction twice as far (below): the lower index wins
            [*direction(22.5, 12.0, 9.0), 0.5],  # above the field of view
        ],
        dtype=np.float32,
    )
    points[3, :3] = 2 * points[2, :3]
    labels = np.array([10, 40 | (7 << 16), 50, 70, 80], dtype=np.uint32)
    source = load_profile("semantickitti")
    out, raw, stats = adapt_scan(points, labels, source, small_target(tmp_path))
    np.testing.assert_array_equal(out[:, :4], points[[1, 2]])
    np.testing.assert_array_equal(raw, labels[[1, 2]])
    np.testing.assert_array_equal(out[:, 4], [1, 3])
    assert (stats.points_kept, stats.dropped_collisions, stats.dropped_fov) == (2, 2, 1)
    assert stats.points_in == 5 and stats.dropped_range == 0


def test_uneven_beams_take_the_nearest_beams_row_within_half_a_spacing(tmp_path: Path) -> None:
    # Beams at 9, 8, 2 and -10 degrees: bands 8.5..9.5, 5..8.5, -4..5 and -10..-4.
    target = small_target(tmp_path, beam_angles=[9.0, 8.0, 2.0, -10.0])
    elevations = [9.8, 6.0, -5.0, 4.9, 9.2]
    points = np.array(
        [[*direction(10.0 + 40 * i, e, 10.0), 0.5] for i, e in enumerate(elevations)],
        dtype=np.float32,
    )
    labels = np.full(len(points), 40, dtype=np.uint32)
    out, _, stats = adapt_scan(points, labels, load_profile("semantickitti"), target)
    np.testing.assert_array_equal(out[:, :4], points[1:])
    np.testing.assert_array_equal(out[:, 4], [1, 3, 2, 0])
    assert stats.dropped_fov == 1
    # Even rows of 5 degrees would have put them in rows 0, 3, 1 and 0.
    assert project(points[1:], 4, 8, 10.0, -10.0).proj_y.tolist() == [0, 3, 1, 0]


def test_a_target_sensor_beyond_the_offset_sees_the_points_moved(tmp_path: Path) -> None:
    points = np.array([[*direction(0.0, 0.0, 10.0), 0.25]], dtype=np.float32)
    out, _, _ = adapt_scan(
        points,
        np.array([40], dtype=np.uint32),
        load_profile("semantickitti"),
        small_target(tmp_path, max_range=5.0),
        offset=(6.0, 0.0, 0.0),
    )
    np.testing.assert_array_equal(out[:, :3], points[:, :3] - np.float32([6, 0, 0]))
    np.testing.assert_array_equal(out[:, 3], points[:, 3])
    _, _, stats = adapt_scan(
        points,
        np.array([40], dtype=np.uint32),
        load_profile("semantickitti"),
        small_target(tmp_path, max_range=5.0),
    )
    assert (stats.points_kept, stats.dropped_range) == (0, 1)
