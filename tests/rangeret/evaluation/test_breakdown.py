"""Results by sequence and by distance band, and `rangeret compare` of reports."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.distance import NUM_BANDS, distance_bands
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import (
    KITTI_LAYOUT,
    discover,
    labels_dir,
    prediction_path,
    velodyne_dir,
)
from rangeret.dataset.profiles import load_profile
from rangeret.dataset.selection import DatasetSelection
from rangeret.evaluation.evaluate import evaluate_predictions
from rangeret.evaluation.metrics import EvaluationReport
from rangeret.io.scans import KITTI_RECORD, read_scan, write_labels, write_scan
from tests.support.reference import add_at_confusion, read_mapped, remap_table, scores
from tests.support.trees import make_tree
from workers.stages import BatchRecord, count_labels, read_and_project, write_results

PNG = b"\x89PNG\r\n\x1a\n"


def _predict_noisily(dataset, preds, sequences, seed=0):
    rng = np.random.default_rng(seed)
    for entry in discover(dataset, sequences, with_labels=True, layout=KITTI_LAYOUT).scans:
        gt = np.fromfile(entry.label_path, dtype=np.uint32)
        pred = gt.copy()
        flip = rng.random(gt.size) < 0.4
        pred[flip] = rng.choice(np.array([10, 40, 50, 70, 3, 300], np.uint32), int(flip.sum()))
        write_labels(prediction_path(preds, entry.sequence, entry.name), pred)


def _evaluate(data, preds, out, *extra):
    code = rangeret_main(
        [
            "evaluate",
            "-q",
            "--dataset",
            str(data),
            "--predictions",
            str(preds),
            "--sequences",
            "03",
            "08",
            "--json",
            str(out / "report.json"),
            *extra,
        ]
    )
    assert code == 0
    return json.loads((out / "report.json").read_text())


def test_parts_add_up_to_the_official_whole(tmp_path, capsys):
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"08": [500, 800, 300], "03": [400, 250]}, seed=4)
    _predict_noisily(data, preds, ["08", "03"])
    report = _evaluate(data, preds, tmp_path, "--plots", str(tmp_path / "plots"))
    printed = capsys.readouterr().out
    assert "0-10 m" in printed and "50+ m" in printed and "\n03 " in printed

    # The official evaluator's numbers, whole and per part, with ranges computed independently.
    cfg = semantickitti()
    table = remap_table(cfg)
    whole = np.zeros((20, 20), np.int64)
    by_seq = {s: np.zeros((20, 20), np.int64) for s in ("03", "08")}
    by_band = np.zeros((NUM_BANDS, 20, 20), np.int64)
    for entry in discover(data, ["03", "08"], with_labels=True, layout=KITTI_LAYOUT).scans:
        gt = read_mapped(entry.label_path, table)
        pred = read_mapped(prediction_path(preds, entry.sequence, entry.name), table)
        whole += add_at_confusion(pred, gt, 20)
        by_seq[entry.sequence] += add_at_confusion(pred, gt, 20)
        ranges = np.linalg.norm(read_scan(entry.scan_path)[:, :3].astype(np.float64), axis=1)
        band = np.digitize(ranges, [10, 20, 30, 40, 50])
        for b in range(NUM_BANDS):
            by_band[b] += add_at_confusion(pred[band == b], gt[band == b], 20)

    miou, _, accuracy = scores(whole, [0])
    np.testing.assert_array_equal(report["confusion"], whole)
    assert abs(report["miou"] - miou) <= 1e-9 and abs(report["accuracy"] - accuracy) <= 1e-9
    assert report["sequences"] == ["03", "08"]

    parts = [(report["per_sequence"][s], by_seq[s]) for s in ("03", "08")]
    parts += list(zip(report["per_distance"], by_band, strict=True))
    assert list(report["per_sequence"]) == ["03", "08"]
    for part, expected in parts:
        np.testing.assert_array_equal(part["confusion"], expected)
        part_miou, part_iou, part_accuracy = scores(expected, [0])
        assert abs(part["miou"] - part_miou) <= 1e-9
        assert abs(part["accuracy"] - part_accuracy) <= 1e-9
        np.testing.assert_allclose(list(part["iou"].values()), part_iou[1:], atol=1e-9, rtol=0)
        assert part["points"] == int(expected[:, 1:].sum())

    evaluated = int(whole[:, 1:].sum())
    for key in ("per_sequence", "per_distance"):
        values = report[key].values() if key == "per_sequence" else report[key]
        np.testing.assert_array_equal(sum(np.array(p["confusion"]) for p in values), whole)
        assert sum(p["points"] for p in values) == evaluated
    assert 0 < evaluated < report["num_points"]
    assert [(p["min_m"], p["max_m"]) for p in report["per_distance"]] == [
        (0, 10),
        (10, 20),
        (20, 30),
        (30, 40),
        (40, 50),
        (50, None),
    ]
    assert EvaluationReport.from_dict(report, config=semantickitti()).to_dict() == report
    for name in ("iou-by-distance.png", "miou-by-sequence.png"):
        png = (tmp_path / "plots" / name).read_bytes()
        assert png[:8] == PNG and len(png) > 10_000


def test_the_pipelines_counts_equal_evaluate(tmp_path):
    """The Ray job's writers (bands from the reader's projection) and its count of scans done
    before a resume (bands from the scan files) give `rangeret evaluate`'s breakdown."""
    data, preds = tmp_path / "data", tmp_path / "pred"
    make_tree(data, {"08": [500, 800], "03": [400]}, seed=7)
    _predict_noisily(data, preds, ["08", "03"], seed=2)
    profile = load_profile(None)
    expected = evaluate_predictions(
        DatasetSelection.named(data, ["03", "08"], KITTI_LAYOUT),
        preds,
        profile=load_profile("semantickitti"),
    ).to_dict()
    keys = ("confusion", "per_sequence", "per_distance")

    entries = discover(data, ["03", "08"], with_labels=True, layout=KITTI_LAYOUT).scans
    record = read_and_project(BatchRecord(0, entries), profile.projection, points=profile.points)
    record.results = [
        (np.fromfile(prediction_path(preds, e.sequence, e.name), np.uint32), None) for e in entries
    ]
    written = write_results(record, str(tmp_path / "again"), profile)
    assert written.failures == [None] * 3
    streamed = written.counts.report(["03", "08"]).to_dict()
    resumed = count_labels(entries, preds, profile).report(["03", "08"]).to_dict()
    for report in (streamed, resumed):
        assert {k: report[k] for k in keys} == {k: expected[k] for k in keys}


def test_points_land_in_their_distance_band(tmp_path):
    np.testing.assert_array_equal(
        distance_bands(np.array([0, 5, 9.999, 10, 15, 49.9, 50, 120], np.float32)),
        [0, 0, 0, 1, 1, 4, 5, 5],
    )
    # (x, y, z), ground truth, prediction; raw ids 10 car, 40 road, 50 building, 70 vegetation,
    # 0 unlabeled (ignored) and 3 (unknown to the label map: ignored as unlabeled).
    points = [
        ((3, 4, 0), 10, 10),  # 5 m
        ((1, 0, 0), 0, 10),  # 1 m, ignored ground truth
        ((0, 0, 2), 3, 40),  # 2 m, unknown ground truth
        ((6, 8, 0), 10, 10),  # 10 m exactly: 10-20
        ((0, 0, 10), 40, 10),  # 10 m exactly
        ((0, 9, 12), 40, 40),  # 15 m
        ((0, 15, 20), 10, 10),  # 25 m
        ((21, 28, 0), 50, 50),  # 35 m
        ((49.9, 0, 0), 50, 50),  # 49.9 m
        ((0, 30, 40), 50, 70),  # 50 m exactly: 50+
        ((72, 96, 0), 70, 70),  # 120 m
        ((0, 96, -72), 0, 70),  # 120 m, ignored ground truth
    ]
    data, preds = tmp_path / "data", tmp_path / "pred"
    xyz = np.array([p for p, _, _ in points], np.float32)
    write_scan(
        velodyne_dir(data, "08", layout=KITTI_LAYOUT) / "000000.bin",
        np.column_stack([xyz, np.zeros(12)]),
        record=KITTI_RECORD,
    )
    write_labels(
        labels_dir(data, "08", layout=KITTI_LAYOUT) / "000000.label",
        np.array([g for _, g, _ in points]),
    )
    write_labels(prediction_path(preds, "08", "000000"), np.array([p for _, _, p in points]))

    report = evaluate_predictions(
        DatasetSelection.named(data, ["08"], KITTI_LAYOUT),
        preds,
        profile=load_profile("semantickitti"),
    ).to_dict()
    bands = report["per_distance"]
    assert [b["points"] for b in bands] == [1, 3, 1, 1, 1, 2]
    assert report["per_sequence"]["08"]["points"] == 9 and report["num_points"] == 12
    assert [sum(map(sum, b["confusion"])) for b in bands] == [3, 3, 1, 1, 1, 3]
    assert bands[0]["iou"]["car"] == pytest.approx(1.0)  # the ignored point predicted car is no FP
    half = pytest.approx(0.5)
    assert bands[1]["iou"]["car"] == half and bands[1]["iou"]["road"] == half
    assert bands[5]["iou"]["building"] == 0 and bands[5]["iou"]["vegetation"] == half
    assert bands[4]["accuracy"] == pytest.approx(1.0) and bands[5]["accuracy"] == half


def _write_report(path, profile, iou, accuracy):
    path.write_text(
        json.dumps(
            {
                "profile": profile,
                "iou": iou,
                "miou": sum(iou.values()) / len(iou),
                "accuracy": accuracy,
            }
        )
    )
    return path


def test_compare_prints_deltas_and_draws_them(tmp_path, capsys):
    base = _write_report(tmp_path / "base.json", "semantickitti", {"car": 0.5, "road": 0.8}, 0.9)
    (tmp_path / "ablation").mkdir()
    other = _write_report(
        tmp_path / "ablation" / "report.json", "semantickitti", {"car": 0.625, "road": 0.7}, 0.85
    )
    png = tmp_path / "compare.png"
    assert rangeret_main(["compare", str(base), str(other), "--out", str(png)]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line.split()[1:] for line in lines[2:] if not line.startswith("-")}
    assert lines[1].split() == ["base", "report", "delta"]
    assert rows["car"] == ["50.00", "62.50", "+12.50"]
    assert rows["road"] == ["80.00", "70.00", "-10.00"]
    assert rows["mIoU"] == ["65.00", "66.25", "+1.25"]
    assert rows["accuracy"] == ["90.00", "85.00", "-5.00"]
    data = png.read_bytes()
    assert data[:8] == PNG and len(data) > 10_000


def test_compare_refuses_reports_that_do_not_compare(tmp_path, capsys):
    base = _write_report(tmp_path / "a.json", "semantickitti", {"car": 0.5, "road": 0.8}, 0.9)
    panda = _write_report(tmp_path / "b.json", "pandaset", {"car": 0.5, "road": 0.8}, 0.9)
    fewer = _write_report(tmp_path / "c.json", "semantickitti", {"car": 0.5}, 0.9)
    (tmp_path / "d.json").write_text("{not json")
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    cases = [
        ([base, tmp_path / "deep.json"], "deep.json is not a JSON evaluation report (it nests"),
        ([base, panda], "b.json is a report of the pandaset profile"),
        ([base, fewer], "c.json evaluates other classes than"),
        ([base, tmp_path / "d.json"], "d.json is not a JSON evaluation report"),
        ([base], "needs at least two reports"),
    ]
    for reports, message in cases:
        assert rangeret_main(["compare", *map(str, reports)]) == 1
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert rangeret_main(["compare", str(base), str(base), "--out", str(tmp_path / "x.jpg")]) == 1
    assert "must end in .png" in capsys.readouterr().err
