"""Point confidences: the softmax probability, at a point's pixel, of the class the point was
finally given (after kNN); written by `rangeret predict --save-confidence` as float16 `.npy` files
beside the predictions, one value per point in [0, 1]."""

from __future__ import annotations

import numpy as np
import torch

from rangeret.cli.main import main as rangeret_main
from rangeret.dataset.labels import semantickitti
from rangeret.dataset.layout import KITTI_LAYOUT, prediction_path, velodyne_dir
from rangeret.inference.point_labels import point_confidences
from rangeret.inference.predictor import Predictor
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import KITTI_RECORD, read_confidence, read_labels, read_scan, write_scan
from tests.support.paths import data_path
from tests.support.workers import small_weights


def test_a_confidence_is_the_softmax_of_the_final_class_at_the_pixel():
    torch.manual_seed(0)
    logits = torch.randn(2, 5, 3, 4)
    px = [np.array([0, 3, -1]), np.array([1, 1])]
    py = [np.array([0, 2, -1]), np.array([1, 2])]
    classes = [np.array([4, 0, 2]), np.array([1, 3])]
    found = point_confidences(logits, px, py, classes)
    probabilities = torch.softmax(logits, dim=1).numpy()
    assert np.isclose(found[0][0], probabilities[0, 4, 0, 0])
    assert np.isclose(found[0][1], probabilities[0, 0, 2, 3])
    assert found[0][2] == 0.0  # no pixel
    assert np.allclose(found[1], [probabilities[1, 1, 1, 1], probabilities[1, 3, 2, 1]])


def test_without_knn_a_confidence_is_the_pixels_top_probability(tmp_path):
    spec = InferenceSpec(
        checkpoint=str(small_weights(tmp_path)), height=32, width=256, device="cpu", knn=False
    )
    predictor = Predictor.from_spec(spec)
    points = read_scan(data_path("semantickitti-scan", "000000.bin"))[::7]
    projection = predictor.project(points)
    result = predictor.label_projections([projection], with_confidence=True)[0]
    pixel = projection.proj_x >= 0
    assert result.confidence.shape == (len(points),) and result.confidence.dtype == np.float32
    top = torch.softmax(predictor.logits([projection])[0], dim=0).amax(dim=0).numpy()
    np.testing.assert_allclose(
        result.confidence[pixel], top[projection.proj_y[pixel], projection.proj_x[pixel]], rtol=1e-5
    )


def test_predict_saves_one_confidence_per_point_beside_each_prediction(tmp_path):
    weights = small_weights(tmp_path)
    data = tmp_path / "data"
    scan = read_scan(data_path("semantickitti-scan", "000000.bin"))
    for i, step in enumerate((3, 5)):
        write_scan(
            velodyne_dir(data, "08", layout=KITTI_LAYOUT) / f"{i:06d}.bin",
            scan[i::step],
            record=KITTI_RECORD,
        )
    net = ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu"]
    common = ["predict", "--dataset", str(data), "--sequences", "08", *net, "-q"]
    assert rangeret_main([*common, "--out", str(tmp_path / "plain")]) == 0
    assert not (tmp_path / "plain" / "sequences" / "08" / "confidence").exists()
    # A tree predicted without confidences gets them on a second run that asks for them.
    assert rangeret_main([*common, "--out", str(tmp_path / "plain"), "--save-confidence"]) == 0
    for i, step in enumerate((3, 5)):
        name = f"{i:06d}"
        path = tmp_path / "plain" / "sequences" / "08" / "confidence" / f"{name}.npy"
        assert np.load(path).dtype == np.float16
        values = read_confidence(path, num_points=len(scan[i::step]))
        assert ((values >= 0) & (values <= 1)).all() and values.max() > 0
        assert len(read_labels(prediction_path(tmp_path / "plain", "08", name))) == values.size


def test_calibration_bins_add_up_and_give_the_expected_calibration_error():
    from rangeret.evaluation.calibration import Calibration

    confidence = np.array([0.05, 0.15, 0.95, 0.95, 1.0, 0.55])
    correct = np.array([False, True, True, False, True, True])
    whole = Calibration()
    whole.add(confidence, correct)
    parts = Calibration()
    for half in (slice(0, 3), slice(3, 6)):
        part = Calibration()
        part.add(confidence[half], correct[half])
        parts.merge(part)
    assert parts.to_dict() == whole.to_dict()
    report = whole.to_dict()
    assert report["points"] == 6 and sum(b["points"] for b in report["bins"]) == 6
    top = report["bins"][9]  # 0.95, 0.95 and 1.0 (the last bin holds 1.0)
    assert top["points"] == 3 and np.isclose(top["accuracy"], 2 / 3)
    assert np.isclose(top["confidence"], (0.95 + 0.95 + 1.0) / 3)
    expected = (abs(0 - 0.05) + abs(1 - 0.15) + 3 * abs(2 / 3 - (2.9 / 3)) + abs(1 - 0.55)) / 6
    assert np.isclose(report["ece"], expected)
    assert report["bins"][3]["accuracy"] is None  # an empty bin


def test_evaluate_reports_calibration_where_every_scan_has_confidences(tmp_path):
    import json

    from rangeret.evaluation.calibration import Calibration
    from rangeret.evaluation.metrics import EvaluationReport
    from tests.support.trees import make_tree

    weights = small_weights(tmp_path)
    data = tmp_path / "data"
    make_tree(data, {"08": [300, 400]})
    net = ["--checkpoint", str(weights), "--height", "32", "--width", "256", "--device", "cpu"]
    predict = ["predict", "--dataset", str(data), "--sequences", "08", *net, "-q"]
    evaluate = ["evaluate", "--dataset", str(data), "--sequences", "08", "-q"]
    assert rangeret_main([*predict, "--out", str(tmp_path / "pred"), "--save-confidence"]) == 0
    report_path = tmp_path / "report.json"
    plots = tmp_path / "plots"
    args = [*evaluate, "--predictions", str(tmp_path / "pred"), "--json", str(report_path)]
    assert rangeret_main([*args, "--plots", str(plots)]) == 0
    report = json.loads(report_path.read_text())
    calibration = report["calibration"]
    evaluated = sum(part["points"] for part in report["per_sequence"].values())
    assert calibration["points"] == evaluated == sum(b["points"] for b in calibration["bins"])
    assert 0 <= calibration["ece"] <= 1 and (plots / "calibration.png").stat().st_size > 0
    # The bins' accuracy, weighted by their points, is the overall accuracy.
    correct = sum(b["accuracy"] * b["points"] for b in calibration["bins"] if b["points"])
    assert np.isclose(correct / evaluated, report["accuracy"])
    rebuilt = EvaluationReport.from_dict(report, config=semantickitti()).calibration
    assert isinstance(rebuilt, Calibration) and np.isclose(rebuilt.ece(), calibration["ece"])

    # Without confidences for every scan there is no calibration, and a note says why.
    (tmp_path / "pred" / "sequences" / "08" / "confidence" / "000001.npy").unlink()
    assert rangeret_main([*args]) == 0
    report = json.loads(report_path.read_text())
    assert "calibration" not in report and "confidence files" in " ".join(report["notes"])
