"""Evaluating a predictions tree: the official numbers, and every file problem named."""

from __future__ import annotations

import numpy as np
import pytest

from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, discover, prediction_path
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.selection import DatasetSelection
from rangeret.evaluation.evaluate import EvaluationError, evaluate_predictions
from rangeret.io.scans import write_labels
from tests.support.reference import add_at_confusion, read_mapped, remap_table, scores
from tests.support.trees import make_tree


def _predict_noisily(dataset, preds, sequences, seed=0):
    rng = np.random.default_rng(seed)
    for entry in discover(dataset, sequences, with_labels=True, layout=KITTI_LAYOUT).scans:
        gt = np.fromfile(entry.label_path, dtype=np.uint32)
        pred = gt.copy()
        flip = rng.random(gt.size) < 0.4
        pred[flip] = rng.choice(np.array([10, 40, 50, 70, 3, 300], np.uint32), int(flip.sum()))
        write_labels(prediction_path(preds, entry.sequence, entry.name), pred)


def test_matches_the_official_evaluation(tmp_path):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"08": [500, 800, 300], "03": [400]})
    _predict_noisily(data, preds, ["08", "03"])
    report = evaluate_predictions(
        DatasetSelection.named(data, ["03", "08"], KITTI_LAYOUT),
        preds,
        profile=load_profile("semantickitti"),
    )

    cfg = semantickitti()
    table = remap_table(cfg)
    conf = np.zeros((20, 20), np.int64)
    for entry in discover(data, ["03", "08"], with_labels=True, layout=KITTI_LAYOUT).scans:
        gt = read_mapped(entry.label_path, table)
        pred = read_mapped(prediction_path(preds, entry.sequence, entry.name), table)
        conf += add_at_confusion(pred, gt, 20)
    miou, iou, acc = scores(conf, [0])
    np.testing.assert_array_equal(report.confusion.matrix, conf)
    assert abs(report.miou - miou) <= 1e-9 and abs(report.accuracy - acc) <= 1e-9
    np.testing.assert_allclose(list(report.iou_by_name().values()), iou[1:], atol=1e-9, rtol=0)
    assert report.num_scans == 4 and report.num_points == 2000
    assert report.unknown_prediction_ids > 0


def test_missing_prediction_and_wrong_length_are_named(tmp_path):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"08": [50, 60, 70]})
    _predict_noisily(data, preds, ["08"])
    prediction_path(preds, "08", "000001").unlink()
    with pytest.raises(EvaluationError, match=r"000001\.label is missing"):
        evaluate_predictions(
            DatasetSelection.named(data, ["08"], KITTI_LAYOUT),
            preds,
            profile=load_profile("semantickitti"),
        )
    write_labels(prediction_path(preds, "08", "000001"), np.zeros(59, np.uint32))
    with pytest.raises(
        EvaluationError, match=r"000001\.label: holds 59 labels but the scan has 60"
    ):
        evaluate_predictions(
            DatasetSelection.named(data, ["08"], KITTI_LAYOUT),
            preds,
            profile=load_profile("semantickitti"),
        )


def test_missing_ground_truth_is_named(tmp_path):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"08": [50, 60]})
    _predict_noisily(data, preds, ["08"])
    (data / "sequences" / "08" / "labels" / "000000.label").unlink()
    with pytest.raises(EvaluationError) as info:
        evaluate_predictions(
            DatasetSelection.named(data, ["08", "09"], KITTI_LAYOUT),
            preds,
            profile=load_profile("semantickitti"),
        )
    text = "\n".join(info.value.problems)
    assert "000000.label is missing" in text and "sequence 09 is missing" in text
