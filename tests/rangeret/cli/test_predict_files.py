"""`rangeret predict --files`: the real scan as PCD (ascii, binary, binary_compressed), PLY (ascii,
binary LE and BE), LAS and LAZ gets the labels of its `.bin`; a truncated file of each format is
named in one line while the others are written; run.json records formats, fields and fill; the
labelled copies read back with their labels; `rangeret view` reads a PCD."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rangeret.cli.main import main
from rangeret.io.ply import read_ply
from rangeret.io.point_files import read_point_file
from rangeret.io.scans import KITTI_RECORD, read_confidence, read_labels, read_scan, write_scan
from tests.support.paths import REPO
from tests.support.point_files import las_decoded, pcd_bytes, write_all_formats
from tests.support.workers import small_weights

NET = ["--height", "32", "--width", "256", "--device", "cpu", "-q"]


@pytest.fixture(scope="module")
def run(tmp_path_factory, real_scan_path) -> dict:
    """Every format of the real scan, plus the `.bin` of what the LAS files hold, labelled by one
    `rangeret predict --files` run (exit 0) with confidences and labelled copies."""
    base = tmp_path_factory.mktemp("predict-files")
    weights = small_weights(base)
    points = read_scan(real_scan_path)
    inputs = base / "in"
    paths = write_all_formats(points, inputs)
    write_scan(inputs / "scan.bin", points, record=KITTI_RECORD)
    # LAS holds coordinates at 0.1 mm and intensity as uint16: its reference is the .bin of the
    # points as decoded from the LAS file, not the original float32 values.
    write_scan(inputs / "las-ref.bin", las_decoded(paths["las"].read_bytes()), record=KITTI_RECORD)
    out = base / "out"
    args = ["predict", "--files", str(inputs), "--out", str(out), "--checkpoint", str(weights)]
    code = main([*args, "--save-confidence", "--write-labelled", *NET])
    return {"base": base, "weights": weights, "paths": paths, "out": out, "code": code}


def test_every_format_gets_the_labels_of_its_bin(run):
    assert run["code"] == 0
    out = run["out"]
    reference = read_labels(out / "scan.label")
    las_reference = read_labels(out / "las-ref.label")
    assert len(reference) == 123_389 and len(np.unique(reference)) > 3
    for kind in run["paths"]:
        expected = las_reference if kind in ("las", "laz") else reference
        assert np.array_equal(read_labels(out / f"{kind}.label"), expected), kind
        confidence = read_confidence(out / f"{kind}.npy", 123_389)
        assert np.array_equal(confidence, read_confidence(out / "scan.npy")) or kind in (
            "las",
            "laz",
        )


def test_run_json_records_each_file(run):
    record = json.loads((run["out"] / "run.json").read_text())
    assert record["runner"] == "rangeret predict --files" and record["dataset"] is None
    assert record["reflectance_fill"] == pytest.approx(0.21)
    by_name = {Path(i["file"]).stem: i for i in record["inputs"]}
    assert set(by_name) == {*run["paths"], "scan", "las-ref"}
    pcd = by_name["pcd-compressed"]
    assert (pcd["format"], pcd["encoding"], pcd["points"]) == ("pcd", "binary_compressed", 123_389)
    assert pcd["fields"] == {"x": "x", "y": "y", "z": "z", "remission": "intensity"}
    assert pcd["invalid_points"] == 0
    assert by_name["ply-be"]["encoding"] == "binary_big_endian"
    laz = by_name["laz"]
    assert laz["format"] == "laz" and "intensity / 65535" in " ".join(laz["notes"])
    assert by_name["scan"]["format"] == "bin"


def test_labelled_copies_read_back_with_their_labels(run):
    out = run["out"]
    for kind, path in run["paths"].items():
        labels = read_labels(out / f"{kind}.label")
        copy = out / f"{kind}.labelled{path.suffix}"
        back = read_point_file(copy, record=KITTI_RECORD)
        original = read_point_file(path, record=KITTI_RECORD)
        assert back.format == original.format and back.encoding == original.encoding, kind
        assert np.array_equal(back.columns["label"], labels), kind
        assert back.columns["confidence"].dtype == np.float32
        assert np.array_equal(back.columns["x"], original.columns["x"]), kind
    assert not list(out.glob("scan.labelled*"))  # a .bin's labelled form is its .label


def test_truncated_files_are_named_and_the_others_still_written(run, capsys):
    base, folder = run["base"], run["base"] / "broken"
    folder.mkdir()
    for kind, path in run["paths"].items():
        data = path.read_bytes()
        (folder / f"{kind}{path.suffix}").write_bytes(data[: len(data) - 7000])
    good = folder / "good.pcd"
    good.write_bytes(run["paths"]["pcd-binary"].read_bytes())
    out = base / "broken-out"
    args = ["predict", "--files", str(folder), "--out", str(out)]
    capsys.readouterr()
    assert main([*args, "--checkpoint", str(run["weights"]), *NET]) == 1
    err = capsys.readouterr().err
    assert "8 of 9 files could not be labelled" in err.splitlines()[0]
    for kind, path in run["paths"].items():
        lines = [line for line in err.splitlines() if f"{kind}{path.suffix}:" in line]
        assert len(lines) == 1 and "Traceback" not in err, (kind, err)
    assert "truncated" in err
    assert read_labels(out / "good.label").shape == (123_389,)
    assert not (out / "pcd-ascii.label").exists()
    record = json.loads((out / "run.json").read_text())
    assert sum("error" in i for i in record["inputs"]) == 8


def test_a_cloud_of_x_y_z_only_gets_the_fill_value_and_fields_map(run, real_scan_path, capsys):
    base = run["base"] / "xyz"
    base.mkdir()
    points = read_scan(real_scan_path)[::40]
    (base / "xyz.pcd").write_bytes(pcd_bytes(points[:, :3], "binary", ("x", "y", "z")))
    (base / "odd.pcd").write_bytes(pcd_bytes(points, "binary", ("x", "y", "z", "reflect")))
    out = base / "out"
    args = ["predict", "--files", str(base / "xyz.pcd"), str(base / "odd.pcd"), "--out", str(out)]
    assert main([*args, "--checkpoint", str(run["weights"]), *NET]) == 0
    record = {Path(i["file"]).stem: i for i in json.loads((out / "run.json").read_text())["inputs"]}
    assert record["xyz"]["fields"]["remission"] == "fill 0.21"
    assert record["odd"]["fields"]["remission"] == "fill 0.21"  # 'reflect' is no alias
    mapped = ["predict", "--files", str(base / "odd.pcd"), "--out", str(base / "mapped")]
    mapped += ["--checkpoint", str(run["weights"]), *NET]
    assert main([*mapped, "--field", "remission=reflect"]) == 0
    record = json.loads((base / "mapped" / "run.json").read_text())
    assert record["field_overrides"] == {"remission": "reflect"}
    assert record["inputs"][0]["fields"]["remission"] == "reflect"
    capsys.readouterr()
    assert main([*mapped, "--field", "colour=reflect"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "colour" in err and "not a value of the point record" in err


def test_two_inputs_with_one_stem_are_refused_up_front(run, capsys):
    a, b = run["paths"]["pcd-binary"], run["base"] / "pcd-binary.ply"
    b.write_bytes(run["paths"]["ply-le"].read_bytes())
    out = run["base"] / "stem-out"
    args = ["predict", "--files", str(a), str(b), "--out", str(out)]
    assert main([*args, "--checkpoint", str(run["weights"]), *NET]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(a) in err and str(b) in err and "same stem" in err
    assert not out.exists()


def test_rangeret_view_reads_a_pcd(run, capsys):
    out = run["base"] / "view.ply"
    labels = run["out"] / "pcd-compressed.label"
    args = ["view", "-q", str(run["paths"]["pcd-compressed"]), "--labels", str(labels)]
    assert main([*args, "--out", str(out)]) == 0
    assert "123,389 points" in capsys.readouterr().out
    cloud = read_ply(out)
    assert np.array_equal(cloud["label"], read_labels(labels) & 0xFFFF)
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"


#: `rangeret ARGV` with the `files` extra's modules made unimportable.
WITHOUT_FILES = """\
import sys
for name in ("pypcd4", "laspy", "lazrs"):
    sys.modules[name] = None
from rangeret.cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def test_without_the_files_extra_pcd_stops_with_one_line_and_ply_still_reads(run, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}

    def view(path: Path) -> subprocess.CompletedProcess:
        argv = ["view", "-q", str(path), "--out", str(tmp_path / f"{path.stem}.png")]
        return subprocess.run(
            [sys.executable, "-c", WITHOUT_FILES, *argv],
            env=env, capture_output=True, text=True, timeout=300, check=False,
        )  # fmt: skip

    blocked = view(run["paths"]["pcd-binary"])
    assert blocked.returncode == 1
    lines = [line for line in blocked.stderr.splitlines() if "ros2" not in line]
    assert lines == [
        "reading PCD files needs the files extra: pip install 'rangeret-service[files]'"
    ], blocked.stderr
    assert view(run["paths"]["ply-be"]).returncode == 0
