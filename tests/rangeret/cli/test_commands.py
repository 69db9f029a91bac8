"""The `rangeret` command: evaluate, submission and validate-submission, as users run them."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np

from rangeret.cli.main import main
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import discover, prediction_path, velodyne_dir
from rangeret.io.scans import write_labels
from rangeret.submission.archives import TEST_SEQUENCES
from tests.support.trees import make_tree


def _copy_truth_as_predictions(data, preds, sequences):
    cfg = semantickitti()
    for e in discover(data, sequences, with_labels=True).scans:
        gt = np.fromfile(e.label_path, dtype=np.uint32)
        write_labels(prediction_path(preds, e.sequence, e.name), cfg.to_raw(cfg.to_class(gt)))


def test_evaluate_command_writes_report_and_plots(tmp_path):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"08": [400, 500]})
    _copy_truth_as_predictions(data, preds, ["08"])
    exe = shutil.which("rangeret") or str(Path(sys.executable).with_name("rangeret"))
    run = subprocess.run(
        [
            exe,
            "evaluate",
            "-q",
            "--dataset",
            data,
            "--predictions",
            preds,
            "--split",
            "valid",
            "--json",
            tmp_path / "r.json",
            "--plots",
            tmp_path / "plots",
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    assert "mIoU" in run.stdout and "traffic-sign" in run.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["accuracy"] == 1.0 and report["num_scans"] == 2
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == [
        "confusion.png",
        "iou-by-distance.png",
        "iou.png",
        "miou-by-sequence.png",
    ]


def test_evaluate_reports_missing_files_in_one_line(tmp_path, capsys):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"05": [40, 50]})
    _copy_truth_as_predictions(data, preds, ["05"])
    prediction_path(preds, "05", "000001").unlink()
    code = main(
        ["evaluate", "-q", "--dataset", str(data), "--predictions", str(preds), "--sequences", "5"]
    )
    err = capsys.readouterr().err
    assert code == 1
    first = err.splitlines()[0]
    assert first.startswith("rangeret evaluate: error: 1 problem(s), the first: ")
    assert "05/predictions/000001.label is missing" in first
    assert "Traceback" not in err


def test_bad_scan_is_one_line_error(tmp_path, capsys):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"08": [10]})
    _copy_truth_as_predictions(data, preds, ["08"])
    (velodyne_dir(data, "08") / "000000.bin").write_bytes(b"\x00" * 20)
    assert (
        main(
            [
                "evaluate",
                "-q",
                "--dataset",
                str(data),
                "--predictions",
                str(preds),
                "--split",
                "valid",
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert "000000.bin" in err and "multiple of 16" in err and "Traceback" not in err


def test_missing_dataset_is_one_line_error(tmp_path, capsys):
    code = main(
        [
            "evaluate",
            "-q",
            "--dataset",
            str(tmp_path / "nope"),
            "--predictions",
            str(tmp_path),
            "--split",
            "valid",
        ]
    )
    assert code == 1
    assert "sequence 08 is missing" in capsys.readouterr().err


def test_submission_and_validation_commands(tmp_path, capsys):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"11": [20], "21": [30, 31]})
    _copy_truth_as_predictions(data, preds, ["11", "21"])
    out = tmp_path / "s.zip"
    base = ["--predictions", str(preds), "--dataset", str(data), "--out", str(out)]
    assert main(["submission", "-q", *base]) == 1
    err = capsys.readouterr().err
    assert "official test sequence 11 has 921" in err and not out.exists()

    assert main(["submission", "-q", *base, "--allow-partial", "--description", "x"]) == 0
    assert "valid partial archive" in capsys.readouterr().out
    assert (
        main(["validate-submission", "-q", str(out), "--dataset", str(data), "--allow-partial"])
        == 0
    )
    assert main(["validate-submission", "-q", str(out), "--dataset", str(data)]) == 1
    assert "would be refused" in capsys.readouterr().err

    with zipfile.ZipFile(out) as zin, zipfile.ZipFile(tmp_path / "flat.zip", "w") as zout:
        for info in zin.infolist():
            if not info.filename.endswith("/"):
                zout.writestr(info, zin.read(info))
    code = main(
        [
            "validate-submission",
            "-q",
            str(tmp_path / "flat.zip"),
            "--dataset",
            str(data),
            "--allow-partial",
        ]
    )
    err = capsys.readouterr().err
    assert code == 1 and "directory entry 'sequences/' is missing" in err
    assert err.count("\n  - ") == 2 * len(TEST_SEQUENCES) + 1


def test_light_commands_start_without_torch():
    code = (
        "import sys; from rangeret.cli.main import build_parser; "
        "build_parser('evaluate').parse_args(['evaluate', '--dataset', 'd', '--predictions', 'p', '--split', 'valid']); "
        "print('torch' in sys.modules)"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "False"


def test_every_entry_point_reports_errors_the_same_way(tmp_path, capsys):
    from workers.predict_job import main as job_main

    args = [
        "--dataset",
        str(tmp_path / "nope"),
        "--split",
        "valid",
        "--out",
        str(tmp_path / "out"),
        "-q",
    ]
    assert job_main(args) == 1
    job = capsys.readouterr().err.splitlines()
    assert main(["predict", *args]) == 1
    cli = capsys.readouterr().err.splitlines()
    assert job[0].startswith("predict_job: error: ") and cli[0].startswith(
        "rangeret predict: error: "
    )
    assert job[0].split(": error: ")[1] == cli[0].split(": error: ")[1]
    assert "sequence 08 is missing" in job[0]
