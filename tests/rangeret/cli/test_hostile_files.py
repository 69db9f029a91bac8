"""Hostile point-cloud files on the command line: `rangeret predict --files` names each one in one
line and writes every good file of its batch, within --max-decoded-bytes (its peak memory
measured against a run of the good files alone); `rangeret view` takes the same bound; a `.bin`
holding NaN is a named failure of `--dataset` and `--files`; oversized range images and a run.json
nested 100,000 deep are one line."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from rangeret.cli.main import main
from rangeret.dataset.layout import KITTI_LAYOUT, velodyne_dir
from rangeret.io.scans import KITTI_RECORD, read_labels, read_scan, write_scan
from tests.support.hostile_files import (
    bad_lzf_pcd,
    colliding_pcd,
    count_bomb_pcd,
    huge_laz,
    short_ascii_pcd,
    vlr_bomb_las,
    wide_compressed_pcd,
)
from tests.support.memory import run_measured
from tests.support.paths import REPO
from tests.support.point_files import pcd_bytes
from tests.support.workers import build_tree, small_weights

NET = ["--height", "32", "--width", "256", "--device", "cpu", "-q"]
MIB = 1 << 20
LIMIT = 48 * MIB
#: What each hostile file's line in the summary says.
HOSTILE = {
    "collide.pcd": "both give the column 'i__0000'",
    "short.pcd": "holds 1 point, the header declares 20 (the file is truncated)",
    "huge.laz": "points of 30 bytes), over the limit of 50,331,648 (--max-decoded-bytes)",
    "count.pcd": "declares 20,000,000 values per point",
    "vlrs.las": "declares 1,000,000 VLRs",
    "lzf.pcd": "does not decompress to the 1,024 bytes its size word declares",
    "overflow.pcd": "its LZF stream is corrupt",
    "wide-over.pcd": "would decode to 51,200,000 bytes (12,500 points of 4,096 bytes)",
    "nan.bin": "point(s) hold non-finite values (NaN or infinity)",
}


@pytest.fixture(scope="module")
def files(tmp_path_factory, real_scan_path) -> dict:
    """The small weights, a good PCD and a wide compressed one within the bound, and the
    hostile files, in a folder each (good ones last, so that a batch that stops early fails)."""
    base = tmp_path_factory.mktemp("hostile")
    good, hostile = base / "good", base / "hostile"
    good.mkdir()
    hostile.mkdir()
    points = read_scan(real_scan_path)[::10]
    nan = points.copy()
    nan[7, 1] = np.nan
    contents = {
        "collide.pcd": colliding_pcd(),
        "short.pcd": short_ascii_pcd(1, 20),
        "huge.laz": huge_laz(2**40),
        "count.pcd": count_bomb_pcd(20_000_000),
        "vlrs.las": vlr_bomb_las(1_000_000),
        "lzf.pcd": bad_lzf_pcd(overflowing=False),
        "overflow.pcd": bad_lzf_pcd(overflowing=True),
        "wide-over.pcd": wide_compressed_pcd(12_500),
        "nan.bin": nan.tobytes(),
    }
    for name, data in contents.items():
        (hostile / name).write_bytes(data)
    (good / "zz-scan.pcd").write_bytes(pcd_bytes(points, "binary_compressed"))
    (good / "zz-wide.pcd").write_bytes(wide_compressed_pcd(10_000))
    return {"base": base, "weights": small_weights(base), "good": good, "hostile": hostile}


def _predict_files(files: dict, out: Path, inputs: list[Path]):
    argv = [sys.executable, "-m", "rangeret.cli", "predict", "--files", *map(str, inputs)]
    argv += ["--out", str(out), "--checkpoint", str(files["weights"]), *NET]
    argv += ["--max-decoded-bytes", str(LIMIT)]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    return run_measured(argv, env=env, cwd=REPO, log=out.with_suffix(".log"))


def test_a_batch_names_each_hostile_file_and_writes_every_good_one(files):
    good = sorted(files["good"].iterdir())
    hostile = sorted(files["hostile"].iterdir())
    alone = _predict_files(files, files["base"] / "alone", good)
    assert alone.returncode == 0, alone.stderr
    out = files["base"] / "batch"
    batch = _predict_files(files, out, [*hostile, *good])
    assert batch.returncode == 1 and "Traceback" not in batch.stderr, batch.stderr
    lines = batch.stderr.splitlines()
    summary = f"{len(hostile)} of {len(hostile) + 2} files could not be labelled"
    assert sum(summary in line for line in lines) == 1, batch.stderr
    for name, problem in HOSTILE.items():
        said = [line for line in lines if f"{name}:" in line]
        assert len(said) == 1 and problem in said[0], (name, batch.stderr)
    for path in good:
        labels = read_labels(out / f"{path.stem}.label")
        assert np.array_equal(labels, read_labels(files["base"] / "alone" / f"{path.stem}.label"))
    assert len(read_labels(out / "zz-wide.label")) == 10_000
    record = json.loads((out / "run.json").read_text())
    assert sum("error" in i for i in record["inputs"]) == len(hostile)
    growth = batch.peak_bytes - alone.peak_bytes
    print(f"peak: good files alone {alone.peak_bytes / MIB:.0f} MiB, with the hostile ones "
          f"{batch.peak_bytes / MIB:.0f} MiB ({growth / MIB:+.0f} MiB)")  # fmt: skip
    assert growth < LIMIT, growth


def test_view_takes_the_same_bound(files, tmp_path, capsys):
    wide, over = files["good"] / "zz-wide.pcd", files["hostile"] / "wide-over.pcd"
    limit = ["--max-decoded-bytes", str(LIMIT)]
    assert main(["view", "-q", str(wide), "--out", str(tmp_path / "w.png"), *limit]) == 0
    assert "10,000 points" in capsys.readouterr().out
    assert main(["view", "-q", str(over), "--out", str(tmp_path / "o.png"), *limit]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "over the limit of 50,331,648 (--max-decoded-bytes)" in err
    assert main(["view", "-q", str(files["hostile"] / "count.pcd"), "--out", str(tmp_path / "c.png")]) == 1  # fmt: skip
    assert "20,000,000 values per point" in capsys.readouterr().err
    assert not (tmp_path / "o.png").exists() and not (tmp_path / "c.png").exists()


def test_a_bin_holding_nan_is_a_named_failure_of_a_dataset_run(files, capsys):
    data = build_tree(files["base"] / "tree", labelled=2, unlabelled=0)
    scan = velodyne_dir(data, "08", layout=KITTI_LAYOUT) / "000001.bin"
    points = read_scan(scan, KITTI_RECORD)
    points[3, 0] = np.inf
    write_scan(scan, points, record=KITTI_RECORD)
    out = files["base"] / "tree-pred"
    argv = ["predict", "--dataset", str(data), "--sequences", "08", "--out", str(out)]
    assert main([*argv, "--checkpoint", str(files["weights"]), *NET]) == 1
    told = capsys.readouterr()
    assert "Traceback" not in told.err and "1 of 2 scans could not be predicted" in told.err
    said = [line for line in told.out.splitlines() if "non-finite" in line]
    assert said == [
        f"FAILED 08/000001: {scan}: 1 point(s) hold non-finite values (NaN or infinity), the "
        "first at point index 3"
    ], told.out
    assert len(list(out.rglob("*.label"))) == 1


@pytest.mark.parametrize(
    ("option", "problem"),
    [("--height", "--height must be at most 512, got 100000"),
     ("--width", "--width must be at most 8192, got 100000")],
)  # fmt: skip
def test_oversized_range_images_are_one_line(files, tmp_path, capsys, option, problem):
    sizes = {"--height": "32", "--width": "256", option: "100000"}
    argv = ["predict", "--files", str(files["good"] / "zz-scan.pcd"), "--out", str(tmp_path)]
    argv += ["--checkpoint", str(files["weights"]), "--device", "cpu", "-q"]
    assert main([*argv, *(part for item in sizes.items() for part in item)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and problem in err


def test_a_run_json_nested_100000_deep_is_one_line(files, tmp_path, capsys):
    (tmp_path / "run.json").write_text("[" * 100_000 + "]" * 100_000)
    argv = ["predict", "--files", str(files["good"] / "zz-scan.pcd"), "--out", str(tmp_path)]
    assert main([*argv, "--checkpoint", str(files["weights"]), *NET]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "run.json is not a readable run record (it nests too" in err
