"""The confusion matrix and the benchmark's IoU, mIoU and accuracy."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rangeret.dataset.distance import scan_bands
from rangeret.dataset.labels import semantickitti
from rangeret.evaluation.counting import RawLabelEvaluator
from rangeret.evaluation.metrics import (
    ConfusionMatrix,
    EvaluationReport,
    confusion_counts,
)
from rangeret.evaluation.plots import write_plots
from rangeret.io.scans import read_labels, read_scan
from tests.support.reference import add_at_confusion, scores


def test_hand_computed_case():
    cm = ConfusionMatrix(num_classes=3, ignore=(0,))
    cm.add(np.array([1, 2, 2, 2, 1]), np.array([1, 1, 2, 2, 0]))
    # C[pred, gt]: (1,1)=1 (2,1)=1 (2,2)=2 (1,0)=1; the gt=0 column is ignored.
    assert cm.matrix.tolist() == [[0, 0, 0], [1, 1, 0], [0, 1, 2]]
    tp, fp, fn = cm.stats()
    assert tp.tolist() == [0, 1, 2] and fp.tolist() == [0, 0, 1] and fn.tolist() == [0, 1, 0]
    assert cm.iou()[1:].tolist() == pytest.approx([1 / 2, 2 / 3])
    assert cm.miou() == pytest.approx((1 / 2 + 2 / 3) / 2)
    assert cm.accuracy() == pytest.approx(3 / 4)


def test_absent_classes_count_as_zero_in_miou():
    cm = ConfusionMatrix(20, (0,))
    cm.add(np.array([1, 1, 9]), np.array([1, 1, 9]))
    assert cm.miou() == pytest.approx(2 / 19)
    assert cm.accuracy() == pytest.approx(1.0)


def test_merging_by_addition_equals_one_pass():
    rng = np.random.default_rng(1)
    pred, gt = rng.integers(0, 20, 10_000), rng.integers(0, 20, 10_000)
    whole = ConfusionMatrix()
    whole.add(pred, gt)
    a, b = ConfusionMatrix(), ConfusionMatrix()
    a.add(pred[:3000], gt[:3000])
    b.add(pred[3000:], gt[3000:])
    np.testing.assert_array_equal((a + b).matrix, whole.matrix)
    a.merge(b.matrix)
    np.testing.assert_array_equal(a.matrix, whole.matrix)


def test_bincount_matches_add_at():
    rng = np.random.default_rng(2)
    pred, gt = rng.integers(0, 20, 50_000), rng.integers(0, 20, 50_000)
    np.testing.assert_array_equal(confusion_counts(pred, gt, 20), add_at_confusion(pred, gt, 20))
    with pytest.raises(ValueError, match=r"0\.\.19"):
        confusion_counts(np.array([20]), np.array([0]), 20)
    with pytest.raises(ValueError, match="3 predictions for 2"):
        confusion_counts(np.zeros(3, int), np.zeros(2, int), 20)


@pytest.fixture(scope="module")
def real_gt(real_label_path):
    return read_labels(real_label_path)


@pytest.fixture(scope="module")
def real_bands(real_scan_path):
    return scan_bands(read_scan(real_scan_path))


def test_perfect_predictions_on_the_real_scan(real_gt, real_bands):
    cfg = semantickitti()
    ev = RawLabelEvaluator(config=semantickitti())
    perfect = cfg.to_raw(cfg.to_class(real_gt))
    ev.add(perfect, real_gt, "08", real_bands)
    report = ev.report()
    present = set(np.unique(cfg.to_class(real_gt)).tolist()) - {0}
    assert report.accuracy == pytest.approx(1.0)
    assert report.miou == pytest.approx(len(present) / 19)
    assert {n for n, v in report.iou_by_name().items() if v > 0.999} == {
        cfg.class_names[c] for c in present
    }


def test_shuffled_predictions_equal_the_official_formulation(real_gt, real_bands):
    cfg = semantickitti()
    rng = np.random.default_rng(3)
    pred = real_gt.copy()
    idx = rng.choice(pred.size, pred.size // 3, replace=False)
    pred[idx] = rng.permutation(pred[idx])
    pred[:500] = rng.choice(np.array(cfg.class_raw_ids, np.uint32), 500)
    ev = RawLabelEvaluator(config=semantickitti())
    ev.add(pred, real_gt, "08", real_bands)
    gt_c, pred_c = cfg.to_class(real_gt).astype(np.int64), cfg.to_class(pred).astype(np.int64)
    ref_conf = add_at_confusion(pred_c, gt_c, 20)
    miou, iou, acc = scores(ref_conf, [0])
    report = ev.report()
    np.testing.assert_array_equal(report.confusion.matrix, ref_conf)
    assert abs(report.miou - miou) < 1e-12
    assert abs(report.accuracy - acc) < 1e-12
    np.testing.assert_allclose(report.confusion.iou(), iou, rtol=0, atol=1e-12)
    assert 0.3 < report.miou < 0.95


def test_unknown_ids_count_as_unlabeled_and_are_reported():
    ev = RawLabelEvaluator(config=semantickitti())
    gt = np.array([10, 10, 40, 40 | (3 << 16), 300], np.uint32)
    pred = np.array([10, 77, 40, 40, 10 | (9 << 16)], np.uint32)
    ev.add(pred, gt, "08", np.zeros(gt.size, np.uint8))
    cm = ev.confusion().matrix
    assert cm[1, 1] == 1 and cm[0, 1] == 1 and cm[9, 9] == 2 and cm[1, 0] == 1
    assert cm.sum() == 5
    assert ev.unknown_prediction_ids == 1
    assert "1 predicted labels held raw ids" in ev.report().notes[0]


def test_report_json_table_and_plots(tmp_path, real_gt, real_bands):
    cfg = semantickitti()
    ev = RawLabelEvaluator(config=semantickitti())
    ev.add(cfg.to_raw(cfg.to_class(real_gt)), real_gt, "08", real_bands)
    report = ev.report(sequences=["08"], checkpoint_sha256="ab" * 32)
    report.write_json(tmp_path / "r" / "report.json")
    data = json.loads((tmp_path / "r" / "report.json").read_text())
    assert set(data) >= {"miou", "accuracy", "iou", "confusion", "checkpoint_sha256"}
    assert list(data["iou"]) == list(cfg.class_names[1:])
    assert np.array(data["confusion"]).shape == (20, 20)
    assert sum(map(sum, data["confusion"])) == real_gt.size  # raw counts, unlabeled column kept
    again = EvaluationReport.from_dict(data, config=semantickitti())
    assert again.miou == report.miou and again.accuracy == report.accuracy
    table = report.table()
    assert "traffic-sign" in table and "mIoU" in table and f"{100 * report.miou:6.2f}" in table
    for path in write_plots(report, tmp_path / "plots", config=semantickitti()):
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert path.stat().st_size > 10_000


def test_the_table_says_which_points_were_predicted_and_which_scored():
    """Points whose ground truth is unlabeled are predicted but scored nowhere: the table's
    totals say both counts, and the per-sequence count is the scored one."""
    ev = RawLabelEvaluator(config=semantickitti())
    gt = np.array([10, 10, 40, 0, 0], np.uint32)
    pred = np.array([10, 40, 40, 40, 10], np.uint32)
    ev.add(pred, gt, "08", np.zeros(gt.size, np.uint8))
    table = ev.report(sequences=["08"]).table()
    assert (
        "1 scans, 5 points predicted, 3 of them scored (the other 2 have the ground truth "
        "unlabeled, which is not scored)"
    ) in table
    header, row = next(
        (line, following)
        for line, following in zip(table.splitlines(), table.splitlines()[1:], strict=False)
        if line.startswith("sequence")
    )
    assert "scored points" in header and row.split()[:2] == ["08", "3"]


def test_a_table_with_every_point_scored_names_one_count():
    ev = RawLabelEvaluator(config=semantickitti())
    labels = np.array([10, 40, 40], np.uint32)
    ev.add(labels, labels, "08", np.zeros(3, np.uint8))
    table = ev.report(sequences=["08"]).table()
    assert "3 points predicted, 3 of them scored\n" in table + "\n" and "the other" not in table


def test_classes_absent_from_the_data_are_grey_columns_in_the_iou_plot(tmp_path):
    """iou.png draws a class with no point predicted or labelled as a grey hatched column (the
    fill 0.92 grey), not as a 0.0 bar; with every class present there is no such column."""
    from matplotlib.image import imread

    from rangeret.evaluation.plots import plot_iou

    cfg = semantickitti()
    grey = round(0.92 * 255)

    def grey_pixels(classes: np.ndarray, name: str) -> int:
        ev = RawLabelEvaluator(config=cfg)
        raw = cfg.to_raw(classes)
        ev.add(raw, raw, "08", np.zeros(raw.size, np.int64))
        image = imread(plot_iou(ev.report(sequences=["08"]), tmp_path / name, config=cfg))
        rgb = np.round(image[..., :3] * 255).astype(int)
        return int(np.all(rgb == grey, axis=-1).sum())

    every = np.repeat(np.arange(1, cfg.num_classes), 10)
    none, one = grey_pixels(every, "every.png"), grey_pixels(every[every != 3], "one-absent.png")
    assert none < 200 and one > 20 * max(none, 100), (none, one)  # antialiasing aside
