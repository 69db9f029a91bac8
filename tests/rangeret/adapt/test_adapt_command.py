"""`rangeret adapt` as a command: unknown raw ids and label maps refused naming the id, an output
folder tied to the input refused, tables layouts refused, and an interrupted run resumed."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from rangeret.adapt import AdaptSettings, LabelMap, adapt_one, finish, plan_adaptation
from rangeret.dataset.profiles import load_profile
from rangeret.io.scans import read_labels
from tests.rangeret.adapt.conftest import SOURCE_SEQUENCES, write_target


def source_ids(source_tree: Path, sequence: str = "00", scan: str = "000000") -> list[int]:
    """The raw ids that occur in one scan of the source tree, sorted."""
    labels = read_labels(source_tree / "sequences" / sequence / "labels" / f"{scan}.label")
    return np.unique(labels & 0xFFFF).tolist()


def options(source_tree: Path, out: Path, target: str | Path, *more: str) -> list[str]:
    """The options of an adapt run of sequences 00 and 08 into `out`."""
    return [
        "--dataset",
        str(source_tree),
        "--profile",
        "semantickitti",
        "--to-profile",
        str(target),
        "--out",
        str(out),
        "--sequences",
        *SOURCE_SEQUENCES,
        *more,
    ]


def test_an_id_the_target_does_not_know_is_named_with_its_scan(source_tree, tmp_path, adapt):
    known = load_profile("pandaset").labels.raw_to_class
    first = next(i for i in source_ids(source_tree) if i not in known)
    code, _, err = adapt(*options(source_tree, tmp_path / "out", "pandaset"))
    assert code == 1
    assert err.splitlines() == [
        f"rangeret adapt: error: 00/000000: raw id {first} is not a raw id of the pandaset "
        "profile's labels; map the source's ids to the target's with --label-map"
    ]


def test_an_id_missing_from_the_label_map_is_named(source_tree, tmp_path, adapt):
    ids = source_ids(source_tree)
    left_out = ids[2]
    path = tmp_path / "map.yaml"
    path.write_text("".join(f"{i}: 7\n" for i in ids if i != left_out))
    code, _, err = adapt(
        *options(source_tree, tmp_path / "out", "pandaset", "--label-map", str(path))
    )
    assert code == 1
    assert err.splitlines() == [
        f"rangeret adapt: error: 00/000000: raw id {left_out} is not in the label map {path}"
    ]


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("[10, 40]\n", "must be a mapping of source raw id: target raw id, got list"),
        ("{}\n", "maps no raw id"),
        ("ten: 7\n", "'ten': a source raw id must be an integer 0..65535"),
        ("70000: 7\n", "70000: a source raw id must be an integer 0..65535"),
        ("10: -1\n", "10: the target raw id must be an integer 0..65535, got -1"),
        ("10: 999\n", "10: 999 is not a raw id of the pandaset profile's labels"),
    ],
)
def test_a_wrong_label_map_is_one_line_naming_the_file(source_tree, tmp_path, adapt, text, problem):
    path = tmp_path / "map.yaml"
    path.write_text(text)
    code, _, err = adapt(
        *options(source_tree, tmp_path / "out", "pandaset", "--label-map", str(path))
    )
    assert code == 1 and err.splitlines() == [f"rangeret adapt: error: {path}: {problem}"]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("where", ["inside", "same", "holding"])
@pytest.mark.parametrize("overwrite", [False, True])
def test_an_output_folder_tied_to_the_dataset_is_refused(
    source_tree, tmp_path, adapt, where, overwrite
):
    out = {
        "inside": source_tree / "sequences" / "adapted",
        "same": source_tree,
        "holding": source_tree.parent,
    }[where]
    before = sorted(str(p) for p in source_tree.rglob("*"))
    target = write_target(tmp_path / "t.yaml")
    extra = ["--overwrite"] if overwrite else []
    code, _, err = adapt(*options(source_tree, out, target, *extra))
    assert code == 1 and len(err.splitlines()) == 1
    assert f"the output folder {out} is, holds or lies inside the dataset {source_tree}" in err
    assert sorted(str(p) for p in source_tree.rglob("*")) == before


@pytest.mark.parametrize(
    ("link", "into"), [("scans", "sequences"), ("scans/000/velodyne", "sequences/00/velodyne")]
)
def test_an_output_whose_folders_lead_into_the_dataset_is_refused(
    source_tree, tmp_path, adapt, link, into
):
    """OUT lies outside the dataset, but a folder under it is a link into the dataset: every
    output path is resolved first, so --overwrite replaces nothing."""
    source = tmp_path / "source"
    shutil.copytree(source_tree, source)
    out = tmp_path / "out"
    (out / link).parent.mkdir(parents=True)
    (out / link).symlink_to(source / into)
    before = {p: p.read_bytes() for p in source.rglob("*") if p.is_file()}
    target = write_target(tmp_path / "t.yaml")
    code, _, err = adapt(*options(source, out, target, "--overwrite"))
    assert code == 1 and len(err.splitlines()) == 1, err
    assert f"inside the dataset {source}" in err and "leads to" in err
    assert {p: p.read_bytes() for p in source.rglob("*") if p.is_file()} == before


def test_a_tables_profile_is_refused_as_coming_later(source_tree, tmp_path, adapt):
    code, _, err = adapt(*options(source_tree, tmp_path / "out", "nuscenes"))
    assert code == 1 and len(err.splitlines()) == 1
    assert "target profile nuscenes reads a version's tables" in err and "comes later" in err


def test_a_second_run_skips_the_scans_already_adapted(source_tree, tmp_path, adapt):
    target = write_target(tmp_path / "t.yaml")
    out = tmp_path / "out"
    argv = options(source_tree, out, target, "--sensor-offset", "0", "0", "0.5")
    assert adapt(*argv)[0] == 0
    scans = sorted(out.glob("scans/*/velodyne/*.bin"))
    labels = sorted(out.glob("scans/*/labels/*.label"))
    assert [p.relative_to(out).as_posix() for p in scans] == [
        "scans/000/velodyne/000000.bin",
        "scans/000/velodyne/000001.bin",
        "scans/008/velodyne/000000.bin",
    ]
    stamps = {p: p.stat().st_mtime_ns for p in scans + labels}
    labels[1].unlink()

    code, stdout, _ = adapt(*argv)
    assert code == 0 and stdout.splitlines()[0] == f"scans adapted into {out}: 1 (2 already there)"
    for path, stamp in stamps.items():
        assert (path.stat().st_mtime_ns == stamp) == (path not in (labels[1], scans[1]))
    info = json.loads((out / "adapt.json").read_text())
    assert info["scans"] == {"chosen": 3, "adapted": 1, "skipped": 2}

    code, _, err = adapt(*options(source_tree, out, target))
    assert code == 1 and err.splitlines() == [
        f"rangeret adapt: error: {out / 'adapt.json'} records another sensor_offset than this "
        "run's; pass --overwrite to adapt into it anyway, or choose another output folder"
    ]
    code, stdout, _ = adapt(*options(source_tree, out, target, "--overwrite"))
    assert code == 0 and stdout.splitlines()[0] == f"scans adapted into {out}: 3"
    assert json.loads((out / "adapt.json").read_text())["sensor_offset"] == [0.0, 0.0, 0.0]


def test_a_scan_that_keeps_no_point_is_left_out(source_tree, tmp_path, adapt):
    target = write_target(tmp_path / "t.yaml", max_range=0.2)
    out = tmp_path / "out"
    code, stdout, _ = adapt(*options(source_tree, out, target))
    assert code == 0 and "3 scan(s) kept no point and were left out" in stdout
    assert not list(out.glob("scans/*/*/*"))
    counts = json.loads((out / "adapt.json").read_text())["counts"]
    assert counts["empty_scans"] == 3 and counts["points_kept"] == 0
    assert counts["dropped_range"] == counts["points_in"]


def test_the_steps_a_ray_job_takes_write_what_the_command_writes(source_tree, tmp_path, adapt):
    target_path = write_target(tmp_path / "t.yaml", ring=True)
    cli, steps = tmp_path / "cli", tmp_path / "steps"
    assert adapt(*options(source_tree, cli, target_path, "--sensor-offset", "1", "0", "0"))[0] == 0
    settings = AdaptSettings(
        load_profile("semantickitti"), load_profile(target_path), (1.0, 0.0, 0.0), None
    )
    plan = plan_adaptation(source_tree, steps, list(SOURCE_SEQUENCES), settings)
    # What a remote worker gets: the job and the settings, pickled.
    jobs, shipped = pickle.loads(pickle.dumps((plan.todo, settings)))
    finish(plan, [adapt_one(job, shipped) for job in jobs])
    written = sorted(p.relative_to(cli) for p in cli.rglob("*.*"))
    assert sorted(p.relative_to(steps) for p in steps.rglob("*.*")) == written
    for path in written:
        if path.name != "adapt.json":
            assert (steps / path).read_bytes() == (cli / path).read_bytes(), path
    by_cli = json.loads((cli / "adapt.json").read_text())
    by_steps = json.loads((steps / "adapt.json").read_text())
    assert by_steps["counts"] == by_cli["counts"] and by_steps["scans"] == by_cli["scans"]
    label_map = pickle.loads(pickle.dumps(LabelMap({40: 7, 44: 7}, "map.yaml")))
    assert label_map.apply(np.array([44, 40])).tolist() == [7, 7]
