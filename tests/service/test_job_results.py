"""A job's result files on their own: the predictions zip's directory entries."""

from __future__ import annotations

import zipfile

import numpy as np

from rangeret.dataset.layout import list_scans, prediction_path
from rangeret.io.scans import write_labels
from rangeret.submission.archives import required_directories
from service.jobs import write_predictions_zip
from tests.support.trees import make_tree


def test_predictions_zip_directory_entries(tmp_path):
    make_tree(tmp_path / "data", {"08": [5], "11": [6]})
    pred = tmp_path / "pred"
    entries = list_scans(tmp_path / "data", ["08", "11"])
    for entry in entries:
        write_labels(
            prediction_path(pred, entry.sequence, entry.name), np.zeros(5, dtype=np.uint32)
        )
    test_only = [e for e in entries if e.sequence == "11"]
    write_predictions_zip(pred, test_only, ["11"], tmp_path / "a.zip", "d")
    write_predictions_zip(pred, entries, ["08", "11"], tmp_path / "b.zip", "d")
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
