"""The single-scan worker that a Serve replica and the in-process gateway run: the labels the
predictor gives, per request options, and one network pass at a time on a shared network."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from rangeret.inference.predictor import Predictor
from rangeret.inference.scan_worker import ScanRequest, ScanWorker
from rangeret.inference.spec import InferenceSpec
from rangeret.io.scans import read_scan
from tests.support.paths import data_path
from tests.support.workers import small_weights


@pytest.fixture(scope="module")
def predictor(tmp_path_factory) -> Predictor:
    weights = small_weights(tmp_path_factory.mktemp("worker"))
    spec = InferenceSpec(checkpoint=str(weights), height=32, width=256, device="cpu")
    return Predictor.from_spec(spec)


@pytest.fixture(scope="module")
def scans() -> list[np.ndarray]:
    points = read_scan(data_path("semantickitti-scan", "000000.bin"))
    return [points[::7], points[1::9]]


def test_scan_worker_labels_batches_as_the_predictor_does(predictor, scans):
    worker = ScanWorker(predictor)
    assert worker.info()["model"] == "rangeret-cir" and worker.profile.name == "semantickitti"
    labels = [r.labels for r in worker.label_requests([ScanRequest(s) for s in scans])]
    expected = [
        r.labels for r in predictor.label_projections([predictor.project(s) for s in scans])
    ]
    assert all(np.array_equal(a, b) for a, b in zip(labels, expected, strict=True))
    raw, sure, plain = worker.label_requests(
        [
            ScanRequest(scans[0], knn=False),
            ScanRequest(scans[0], confidence=True),
            ScanRequest(scans[1]),
        ]
    )
    assert raw.labels.shape == scans[0][:, 0].shape and raw.confidence is None
    assert not np.array_equal(raw.labels, expected[0])  # kNN changes some labels
    assert np.array_equal(sure.labels, expected[0]) and np.array_equal(plain.labels, expected[1])
    assert sure.confidence.shape == expected[0].shape
    assert (sure.confidence >= 0).all() and (sure.confidence <= 1).all()
    bad = worker.label_requests([ScanRequest(scans[0][:, :3]), ScanRequest(scans[1])])
    assert bad[0] == "points must have shape (N, 4), got (17627, 3)"
    assert np.array_equal(bad[1].labels, expected[1])


def test_a_shared_network_runs_one_pass_at_a_time(predictor, scans, monkeypatch):
    """Single scans and a job's batches share the gateway's one network: the predictor and its
    copy without kNN take turns, whatever thread asks."""
    worker = ScanWorker(predictor)
    inside, most = [0], [0]
    forward = Predictor.logits

    def counting(self, projections, times=None):
        inside[0] += 1
        most[0] = max(most[0], inside[0])
        time.sleep(0.05)
        try:
            return forward(self, projections, times)
        finally:
            inside[0] -= 1

    monkeypatch.setattr(Predictor, "logits", counting)
    requests = [[ScanRequest(scans[0])], [ScanRequest(scans[1], knn=False)]]
    threads = [threading.Thread(target=worker.label_requests, args=(r,)) for r in requests * 2]
    threads.append(threading.Thread(target=predictor.predict, args=(scans[0],)))
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert most[0] == 1 and inside[0] == 0
