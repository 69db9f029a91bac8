"""Uploaded nuScenes archives on their own (`rangeret.dataset.table_upload_rules` through
`service.archives.extraction.extract_with`): a simulated tree zipped as it ships is extracted as it was, and
each fault (a member outside the layout, a second version, a sweep or label file the tables do not
name, a keyframe without its sweep, a label file of another length, a scene labelled in part, no
tables) is refused in one sentence before the job sees it."""

from __future__ import annotations

import zipfile
from pathlib import Path

import pytest

from rangeret.dataset.layout import list_scans
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.table_upload_rules import NuScenesRules
from service.archives.extraction import ArchiveError, ArchiveLimits, ArchiveTooLarge, extract_with
from tests.support.nuscenes import entries, write_tree

PROFILE = load_profile("nuscenes")
LIMITS = ArchiveLimits(
    max_bytes=8 << 20, max_members=60, max_points=100_000, max_extracted_bytes=16 << 20
)


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tree(tmp_path_factory.mktemp("nu") / "nu", {"scene-0061": 1, "scene-0103": 2})


def _members(tree: Path) -> dict[str, bytes]:
    """The tree's files as an upload holds them (its map PNG left out)."""
    return {
        p.relative_to(tree).as_posix(): p.read_bytes()
        for p in sorted(tree.rglob("*"))
        if p.is_file() and not p.relative_to(tree).as_posix().startswith("maps/")
    }


def _zip(path: Path, members: dict[str, bytes | None]) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            if data is not None:
                zf.writestr(name, data)
    return path


def _extract(tmp_path: Path, members: dict[str, bytes | None]):
    archive = _zip(tmp_path / "upload", members)
    rules = NuScenesRules(PROFILE.points, PROFILE.layout)
    return extract_with(archive, tmp_path / "data", LIMITS, rules)


def _refused(tmp_path: Path, members: dict[str, bytes | None]) -> str:
    with pytest.raises(ArchiveError) as refused:
        _extract(tmp_path, members)
    detail = str(refused.value)
    assert detail[0].isupper() and detail.endswith(".") and "\n" not in detail
    assert str(tmp_path) not in detail  # the job's folder is never named
    return detail


def test_a_tree_as_it_ships_is_extracted_as_it_was(tmp_path, tree):
    members = _members(tree)
    found = _extract(tmp_path, {"v1.0-mini/": b"", "./samples/LIDAR_TOP/": b"", **members})
    assert found.version == "v1.0-mini" and found.scans == 3
    assert found.sequences == ["scene-0061", "scene-0103"] == found.labelled
    for name, data in members.items():
        assert (found.root / name).read_bytes() == data
    listed = list_scans(found.root, found.sequences, layout=PROFILE.layout, version=found.version)
    assert [e.name for e in listed] == [e.name for e in entries(tree, found.sequences)]


def test_a_tree_without_label_files_has_no_labelled_scene(tmp_path, tree):
    members = {n: d for n, d in _members(tree).items() if not n.startswith("lidarseg/")}
    found = _extract(tmp_path, members)
    assert found.scans == 3 and found.labelled == []


def _label(tree: Path, scene: str, index: int = 0) -> tuple[str, str]:
    """The archive names of a keyframe's label file and sweep."""
    entry = entries(tree, [scene])[index]
    return (
        entry.label_path.relative_to(tree).as_posix(),
        entry.scan_path.relative_to(tree).as_posix(),
    )


def test_each_fault_is_one_sentence_naming_it(tmp_path, tree):
    members = _members(tree)
    label, sweep = _label(tree, "scene-0103")
    second_label, _ = _label(tree, "scene-0103", 1)
    cases = {
        "map": ({"maps/x.png": b"png"}, "'maps/x.png' is not a table"),
        "folder": ({"sweeps/": b""}, "'sweeps/' is a folder outside the nuScenes layout"),
        "version": (
            {"v1.0-test/scene.json": b"[]"},
            "the versions v1.0-mini and v1.0-test",
        ),
        "stray sweep": (
            {"samples/LIDAR_TOP/stray.pcd.bin": members[sweep]},
            "samples/LIDAR_TOP/stray.pcd.bin is not the sweep of a keyframe in "
            "v1.0-mini/sample_data.json",
        ),
        "stray label": (
            {"lidarseg/v1.0-mini/abc_lidarseg.bin": members[label]},
            "lidarseg/v1.0-mini/abc_lidarseg.bin is not the label file of a keyframe",
        ),
        "short label": ({label: members[label][:-1]}, f"{label} holds"),
        "missing sweep": ({sweep: None}, f"{sweep} is missing"),
        "part labelled": ({second_label: None}, "scene scene-0103 has label files for some"),
        "no tables": (
            {n: None for n in members if n.startswith("v1.0-mini/")},
            "holds no nuScenes tables",
        ),
        "bad sweep": ({sweep: members[sweep][:-4]}, f"Archive member {sweep}"),
    }
    for case, (change, words) in cases.items():
        folder = tmp_path / case.replace(" ", "-")
        folder.mkdir()
        assert words in _refused(folder, {**members, **change}), case


def test_the_limits_apply_as_to_every_archive(tmp_path, tree):
    members = _members(tree)
    _, sweep = _label(tree, "scene-0061")
    record = PROFILE.points.point_bytes
    big = {sweep: members[sweep] + b"\0" * record * LIMITS.max_points}
    with pytest.raises(ArchiveTooLarge, match="holds more than 100,000 points"):
        _extract(tmp_path, {**members, **big})
    many = {f"samples/LIDAR_TOP/f{i}/": b"" for i in range(LIMITS.max_members)}
    with pytest.raises(ArchiveError):
        _extract(tmp_path, {**members, **many})
