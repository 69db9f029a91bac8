"""A job's result files on their own: the predictions zip's directory entries and description,
the sequences a report covers, the report and its plots, and which plots a job serves."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, list_scans, prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.selection import DatasetSelection
from rangeret.io.scans import write_labels
from rangeret.submission.archives import required_directories
from service.jobs import JobRecord, write_predictions_zip
from service.jobs.results import (
    labelled_sequences,
    plot_path,
    predictions_description,
    report_plots,
    write_report,
)
from service.schemas import JobState
from tests.support.trees import make_tree

KITTI = load_profile(None)


def test_predictions_zip_directory_entries(tmp_path):
    make_tree(tmp_path / "data", {"08": [5], "11": [6]})
    pred = tmp_path / "pred"
    entries = list_scans(tmp_path / "data", ["08", "11"], layout=KITTI_LAYOUT)
    for entry in entries:
        write_labels(
            prediction_path(pred, entry.sequence, entry.name), np.zeros(5, dtype=np.uint32)
        )
    test_only = [e for e in entries if e.sequence == "11"]
    write_predictions_zip(
        pred, test_only, ["11"], tmp_path / "a.zip", "d", profile=load_profile("semantickitti")
    )
    write_predictions_zip(
        pred, entries, ["08", "11"], tmp_path / "b.zip", "d", profile=load_profile("semantickitti")
    )
    names_a = zipfile.ZipFile(tmp_path / "a.zip").namelist()
    names_b = zipfile.ZipFile(tmp_path / "b.zip").namelist()
    assert [n for n in names_a if n.endswith("/")] == list(required_directories())
    assert [n for n in names_b if n.endswith("/")] == [
        "sequences/",
        "sequences/08/",
        "sequences/08/predictions/",
        "sequences/11/",
        "sequences/11/predictions/",
    ]
    assert "sequences/08/predictions/000000.label" in names_b and "description.txt" in names_a


def test_the_description_names_the_gateway_the_checkpoint_and_the_profile():
    text = predictions_description("cd" * 32, load_profile("pandaset"))
    assert "the rangeret gateway" in text and "cd" * 32 in text and "profile: pandaset" in text


def test_only_sequences_with_every_label_are_evaluated(tmp_path):
    data = tmp_path / "data"
    make_tree(data, {"08": [5, 6], "11": [5]})
    make_tree(data, {"12": [5]}, labelled=False)
    (data / "sequences" / "11" / "labels" / "000000.label").unlink()
    assert labelled_sequences(DatasetSelection.named(data, ["08", "11", "12"], KITTI_LAYOUT)) == [
        "08"
    ]


def test_the_report_and_its_plots_are_written_into_the_job_folder(tmp_path):
    data = tmp_path / "data"
    written = make_tree(data, {"08": [50, 60]})
    pred = tmp_path / "job" / "predictions"
    config = semantickitti()
    for i, labels in enumerate(written["08"]):  # the ground truth itself, as predictions
        truth = config.to_raw(config.to_class(labels)).astype(np.uint32)
        write_labels(prediction_path(pred, "08", f"{i:06d}"), truth)
    path, metrics = write_report(
        DatasetSelection.named(data, ["08"], KITTI_LAYOUT),
        pred,
        tmp_path / "job",
        profile=KITTI,
        checkpoint_sha256="ef" * 32,
        precision="fp16",
        backend="onnxruntime",
    )
    assert path == tmp_path / "job" / "report.json"
    report = json.loads(path.read_text())
    assert (report["precision"], report["backend"]) == ("fp16", "onnxruntime")
    assert report["num_scans"] == 2 and report["miou"] == metrics["miou"] == pytest.approx(1.0)
    assert set(metrics) == {"miou", "accuracy", "iou"} and metrics["accuracy"] == pytest.approx(1.0)
    assert any((tmp_path / "job" / "plots").glob("*.png"))


def _record(tmp_path: Path, state: JobState, report: bool = True) -> JobRecord:
    return JobRecord(
        id="j",
        kind="dataset",
        state=state,
        dataset=str(tmp_path),
        sequences=["08"],
        created=0.0,
        report=str(tmp_path / "report.json") if report else None,
    )


def test_a_succeeded_job_serves_only_its_plots_by_their_names(tmp_path):
    plots = tmp_path / "plots"
    plots.mkdir()
    for name in ("iou-by-class.png", "confusion.png", "Upper.png", "notes.txt"):
        (plots / name).write_bytes(b"x")
    (tmp_path / "secret.png").write_bytes(b"x")
    done = _record(tmp_path, JobState.succeeded)
    assert report_plots(done) == ["confusion.png", "iou-by-class.png"]
    assert plot_path(done, "confusion.png") == plots / "confusion.png"
    assert plot_path(done, "Upper.png") is None and plot_path(done, "../secret.png") is None
    assert report_plots(_record(tmp_path, JobState.running)) == []
    assert report_plots(_record(tmp_path, JobState.succeeded, report=False)) == []
    assert plot_path(_record(tmp_path, JobState.failed), "confusion.png") is None
    assert report_plots(_record(tmp_path / "gone", JobState.succeeded)) == []
