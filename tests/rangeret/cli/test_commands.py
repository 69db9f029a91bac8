"""The `rangeret` command: evaluate, submission and validate-submission, as users run them."""

from __future__ import annotations

import ast
import dataclasses
import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.cli.main import main
from rangeret.commands import CommandError
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, discover, prediction_path, velodyne_dir
from rangeret.evaluation.evaluate import EvaluationError
from rangeret.exceptions import ConfigError, DatasetError, InputError, ModelError, ResourceError
from rangeret.io.scans import ScanFormatError, write_labels
from rangeret.models.weights.checkpoint import CheckpointError
from rangeret.models.weights.hub import WeightsError
from rangeret.submission.archives import TEST_SEQUENCES
from tests.support.trees import make_tree


def _copy_truth_as_predictions(data, preds, sequences):
    cfg = semantickitti()
    for e in discover(data, sequences, with_labels=True, layout=KITTI_LAYOUT).scans:
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
    assert first.startswith("rangeret evaluate: error: ")
    assert "05/predictions/000001.label is missing" in first and len(err.splitlines()) == 1
    assert "Traceback" not in err


def test_bad_scan_is_one_line_error(tmp_path, capsys):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"08": [10]})
    _copy_truth_as_predictions(data, preds, ["08"])
    (velodyne_dir(data, "08", layout=KITTI_LAYOUT) / "000000.bin").write_bytes(b"\x00" * 20)
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
    assert "than the official test set in sequence" in err and "of 921)" in err
    assert err.count("sequences are missing") == 1 and not out.exists()

    assert main(["submission", "-q", *base, "--allow-partial", "--description", "x"]) == 0
    assert "valid partial archive" in capsys.readouterr().out
    assert (
        main(["validate-submission", "-q", str(out), "--dataset", str(data), "--allow-partial"])
        == 0
    )
    assert main(["validate-submission", "-q", str(out), "--dataset", str(data)]) == 1
    err = capsys.readouterr().err
    assert "would be refused" in err
    # Each problem is said once: in the line itself when it is the only one, else in the list.
    lines = err.splitlines()
    problems = [line.removeprefix("  - ") for line in lines if line.startswith("  - ")]
    if problems:
        assert lines[0].endswith(f"would be refused for {len(problems)} problems:")
        assert all(err.count(p) == 1 for p in problems), err
    else:
        assert len(lines) == 1 and err.count("official test sequence") == 1, err

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


def _with_compare_body(monkeypatch, body):
    """Make `rangeret compare` run `body` (its options are the real ones)."""
    from rangeret.cli import main as cli_main

    monkeypatch.setattr(
        cli_main,
        "BUILTIN_COMMANDS",
        tuple(
            dataclasses.replace(c, run=body) if c.name == "compare" else c
            for c in cli_main.BUILTIN_COMMANDS
        ),
    )


def _raising(exc: BaseException):
    def body(args):
        raise exc

    return body


@pytest.mark.parametrize(
    ("exc", "line"),
    [
        (InputError("bad value"), "bad value"),
        (DatasetError("no sequences"), "no sequences"),
        (ConfigError("bad profile"), "bad profile"),
        (ModelError("no weights"), "no weights"),
        (ResourceError("no CUDA"), "no CUDA"),
        (CommandError("refused", ["a", "b"]), "refused"),
        (ScanFormatError("s.bin", "is empty"), "s.bin: is empty"),
        (CheckpointError("c.pt is not a checkpoint"), "c.pt is not a checkpoint"),
        (WeightsError("hub unreachable"), "hub unreachable"),
        (
            EvaluationError(["x is missing", "y is missing"]),
            "2 problems:",
        ),
    ],
    ids=lambda v: type(v).__name__ if isinstance(v, BaseException) else "",
)
def test_each_kind_of_user_error_is_one_line(monkeypatch, capsys, exc, line):
    _with_compare_body(monkeypatch, _raising(exc))
    assert main(["compare", "r.json"]) == 1
    err = capsys.readouterr().err
    assert err.splitlines()[0] == f"rangeret compare: error: {line}"
    assert "Traceback" not in err
    assert err.count("\n  - ") == len(exc.detail_lines())


def test_an_interrupt_is_one_line_and_exit_130(monkeypatch, capsys):
    _with_compare_body(monkeypatch, _raising(KeyboardInterrupt()))
    assert main(["compare", "r.json"]) == 130
    assert capsys.readouterr().err == "rangeret compare: error: interrupted\n"


@pytest.mark.parametrize("exc", [ValueError("a bug"), TypeError("a bug"), FileNotFoundError("f")])
def test_a_programming_error_propagates(monkeypatch, capsys, exc):
    _with_compare_body(monkeypatch, _raising(exc))
    with pytest.raises(type(exc)):
        main(["compare", "r.json"])
    assert ": error: " not in capsys.readouterr().err


def test_a_programming_error_shows_its_traceback_and_fails():
    code = (
        "import dataclasses, sys; from rangeret.cli import main as m\n"
        "def body(args): raise ValueError('a bug in the body')\n"
        "m.BUILTIN_COMMANDS = tuple(dataclasses.replace(c, run=body) if c.name == 'compare' "
        "else c for c in m.BUILTIN_COMMANDS)\n"
        "sys.exit(m.main(['compare', 'r.json']))"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert run.returncode != 0
    assert "Traceback" in run.stderr and "ValueError: a bug in the body" in run.stderr
    assert ": error: " not in run.stderr


def test_the_error_path_imports_only_the_error_hierarchy():
    import rangeret.commands

    tree = ast.parse(Path(rangeret.commands.__file__).read_text())
    project = {
        node.module
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("rangeret")
    } | {
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.Import)
        for alias in node.names
        if alias.name.startswith("rangeret")
    }
    assert project == {"rangeret.exceptions"}


def test_a_missing_input_file_is_one_line(tmp_path, capsys):
    missing = tmp_path / "nope.bin"
    assert main(["view", str(missing), "--out", str(tmp_path / "v.png")]) == 1
    err = capsys.readouterr().err
    assert err == f"rangeret view: error: [Errno 2] No such file or directory: '{missing}'\n"
