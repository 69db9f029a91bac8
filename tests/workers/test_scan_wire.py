"""The single-scan exchange with objects (`panoptic=true`), both ways, and the replica side
that answers it: the same network, the labels and objects `rangeret predict --panoptic` gives."""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch

from rangeret.inference.results import ScanPrediction
from rangeret.io.scans import read_scan
from tests.support.paths import data_path
from workers.scan_wire import (
    CONFIDENCE_HEADER,
    INSTANCES_HEADER,
    POINTS_HEADER,
    decode_labels,
    encode_labels,
    options_query,
)

LABELS = np.array([10, 40, (1 << 16) | 10, (2 << 16) | 30, 44], np.uint32)
INSTANCES = np.array([0, 0, 1, 2, 0], np.uint32)


def test_options_query_names_the_task():
    assert options_query(True, False) == {"knn": "true", "confidence": "false", "panoptic": "false"}
    assert options_query(False, True, panoptic=True)["panoptic"] == "true"


@pytest.mark.parametrize("confidence", [None, np.linspace(0, 1, 5, dtype=np.float32)])
def test_objects_follow_the_labels_and_confidences_and_come_back(confidence):
    body, headers = encode_labels(ScanPrediction(LABELS, confidence, instances=INSTANCES))
    assert headers[INSTANCES_HEADER] == "2" and headers[POINTS_HEADER] == "5"
    arrays = 3 if confidence is not None else 2
    assert len(body) == 4 * 5 * arrays
    assert body[-20:] == INSTANCES.astype("<u4").tobytes()
    back = decode_labels(body, headers, 5)
    assert np.array_equal(back.labels, LABELS) and np.array_equal(back.instances, INSTANCES)
    assert back.num_instances == 2
    if confidence is None:
        assert back.confidence is None
    else:
        assert np.array_equal(back.confidence, confidence)
    again, again_headers = encode_labels(back)
    assert again == body and again_headers == headers


def test_an_answer_without_objects_has_no_instances_header():
    body, headers = encode_labels(ScanPrediction(LABELS))
    assert INSTANCES_HEADER not in headers and len(body) == 20
    assert decode_labels(body, headers, 5).instances is None


def test_answers_whose_objects_do_not_fit_are_refused():
    body, headers = encode_labels(ScanPrediction(LABELS, instances=INSTANCES))
    with pytest.raises(ValueError, match=r"answered 40 bytes for 5 points, not the 60 bytes"):
        decode_labels(body, {**headers, CONFIDENCE_HEADER: "1"}, 5)
    without = {k: v for k, v in headers.items() if k != INSTANCES_HEADER}
    with pytest.raises(ValueError, match=r"not the 20 bytes"):
        decode_labels(body, without, 5)
    with pytest.raises(
        ValueError, match=rf"answered 2 objects, not the 3 of its {INSTANCES_HEADER}"
    ):
        decode_labels(body, {**headers, INSTANCES_HEADER: "3"}, 5)
    with pytest.raises(ValueError, match=rf"{INSTANCES_HEADER} header is not a count: '-1'"):
        decode_labels(body, {**headers, INSTANCES_HEADER: "-1"}, 5)


def _random_kitti_network(path):
    """Random 20-class weights at 32 x 256, whose argmax holds thing classes and so objects."""
    from rangeret.models import build_model

    net = build_model("rangeret-cir", 32, 256, num_classes=20, layers=1).eval()
    g = torch.Generator().manual_seed(3)
    state = {
        k: torch.randn(v.shape, generator=g) * 0.5
        if v.is_floating_point() and not k.endswith("running_var")
        else v
        for k, v in net.state_dict().items()
    }
    torch.save(state, path)
    return path


def test_a_replica_answers_panoptic_requests_as_rangeret_predict_labels(tmp_path):
    """One batch mixing both tasks: each request answered by its own worker (the panoptic one
    sharing the network), the panoptic answer the `Predictor`'s of a --panoptic spec, and the
    answer through the exchange unchanged."""
    pytest.importorskip("ray")
    from rangeret.dataset.profiles import load_profile
    from rangeret.inference.loading import project_scans
    from rangeret.inference.predictor import Predictor
    from rangeret.inference.scan_worker import ScanRequest
    from rangeret.inference.settings import ClusterSettings
    from rangeret.inference.spec import InferenceSpec
    from rangeret.inference.timing import StageTimes
    from rangeret.models import build_model
    from workers.serve_app import ReplicaModel, ScanModel

    weights = _random_kitti_network(tmp_path / "w.pt")
    spec = InferenceSpec(
        checkpoint=str(weights), height=32, width=256, device="cpu", min_cluster_points=5
    )
    clustering = ClusterSettings(spec.cluster_angle, spec.min_cluster_points)
    model = ReplicaModel("default", Predictor.from_spec(spec), lambda _: None, clustering)
    assert model.panoptic_refusal is None
    panoptic_worker = model.worker_for(True)
    assert model.worker_for(True) is panoptic_worker and model.worker_for(False) is model.worker
    assert panoptic_worker.predictor.network is model.worker.predictor.network

    points = read_scan(data_path("semantickitti-scan", "000000.bin"))[::7]
    requests = [ScanRequest(points), ScanRequest(points, confidence=True)]
    replica = types.SimpleNamespace(_failure=None)
    plain, found = ScanModel._label(replica, [model, model], requests, [False, True])
    assert isinstance(plain, ScanPrediction) and isinstance(found, ScanPrediction)
    assert plain.instances is None and found.instances is not None

    reference = Predictor.from_spec(spec.replace(panoptic=True))
    projected = project_scans([points], reference.projection_config, StageTimes())
    (expected,) = reference.label_projections(projected, with_confidence=True)
    assert isinstance(expected, ScanPrediction) and expected.instances is not None
    assert np.array_equal(found.labels, expected.labels)
    assert np.array_equal(found.instances, expected.instances)
    assert np.array_equal(found.confidence, expected.confidence)
    assert np.array_equal(found.labels & 0xFFFF, plain.labels)
    assert found.num_instances > 1

    body, headers = encode_labels(found)
    back = decode_labels(body, headers, len(points))
    assert headers[INSTANCES_HEADER] == str(found.num_instances)
    for name in ("labels", "confidence", "instances"):
        assert np.array_equal(getattr(back, name), getattr(found, name)), name

    torch.manual_seed(0)
    torch.save(
        build_model("rangeret-cir", 64, 128, num_classes=15, layers=1).state_dict(),
        tmp_path / "panda.pt",
    )
    panda = InferenceSpec(
        checkpoint=str(tmp_path / "panda.pt"), width=128, profile="pandaset", device="cpu"
    )
    refused = ReplicaModel("panda", Predictor.from_spec(panda), lambda _: None)
    assert refused.panoptic_refusal == load_profile("pandaset").panoptic_refusal()
