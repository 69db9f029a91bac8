"""The single-scan request batcher: batches up to the batch size within the wait, backend
failures, refused scans, and requests for confidences kept apart in the network passes."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from rangeret.inference.results import ScanPrediction
from rangeret.inference.scan_worker import group_by_options
from service.labelling.batching import ScanBatcher
from service.labelling.errors import BackendError, ScanRejected


class FakeWorker:
    """Labels = the number of points (+1000 without kNN), repeated; one pass per set of equal
    options as the real worker groups them; records every batch and pass; can be told to fail."""

    def __init__(self, delay: float = 0.05) -> None:
        self.delay = delay
        self.batches: list[int] = []
        self.passes: list[tuple[int, bool, bool]] = []
        self.fail = False
        self.in_flight = 0
        self._lock = threading.Lock()

    def label_requests(self, requests):
        with self._lock:
            self.batches.append(len(requests))
            self.in_flight += 1
        try:
            time.sleep(self.delay)
            if self.fail:
                raise RuntimeError("actor died")
            results = [None] * len(requests)
            for indices in group_by_options(requests):
                knn, confidence = requests[indices[0]].options
                self.passes.append((len(indices), knn, confidence))
                for i in indices:
                    n = len(requests[i].points)
                    results[i] = self.one(n, knn, confidence)
            return results
        finally:
            self.in_flight -= 1

    @staticmethod
    def one(n: int, knn: bool, confidence: bool):
        return ScanPrediction(
            np.full(n, n + (0 if knn else 1000), dtype=np.uint32),
            np.full(n, 0.5, dtype=np.float32) if confidence else None,
        )


def _scan(n: int) -> np.ndarray:
    return np.zeros((n, 4), dtype=np.float32)


def _request(n: int, knn: bool = True, confidence: bool = False):
    from rangeret.inference.scan_worker import ScanRequest

    return ScanRequest(_scan(n), knn, confidence)


def test_batcher_gathers_concurrent_requests_up_to_the_batch_size():
    async def run():
        worker = FakeWorker()
        batcher = ScanBatcher(worker, batch_size=4, max_wait=0.05)
        await batcher.start()
        try:
            results = await asyncio.gather(
                *(batcher.label_request(_request(n, knn=n % 2 == 0)) for n in range(1, 12))
            )
        finally:
            await batcher.stop()
        return worker, results

    worker, results = asyncio.run(run())
    for n, labelled in enumerate(results, start=1):
        assert labelled.labels.tolist() == [n + (0 if n % 2 == 0 else 1000)] * n
        assert labelled.confidence is None
    assert all(size <= 4 for size in worker.batches) and sum(worker.batches) == 11
    assert max(worker.batches) > 1 and len(worker.batches) < 11
    assert sum(size for size, _, _ in worker.passes) == 11


def test_batcher_waits_at_most_max_wait_and_not_at_all_for_batch_size_one():
    async def one(batch_size: int) -> float:
        batcher = ScanBatcher(FakeWorker(delay=0), batch_size=batch_size, max_wait=0.2)
        await batcher.start()
        start = time.perf_counter()
        await batcher.label_request(_request(3))
        elapsed = time.perf_counter() - start
        await batcher.stop()
        return elapsed

    assert 0.18 <= asyncio.run(one(4)) < 1.0
    assert asyncio.run(one(1)) < 0.1


def test_batcher_reports_backend_failures_and_keeps_serving():
    async def run():
        worker = FakeWorker(delay=0.01)
        batcher = ScanBatcher(worker, batch_size=2, max_wait=0.01)
        await batcher.start()
        worker.fail = True
        with pytest.raises(BackendError, match="the worker backend failed: actor died"):
            await batcher.label_request(_request(2))
        worker.fail = False
        labels = await batcher.label_request(_request(2))
        await batcher.stop()
        return labels

    assert asyncio.run(run()).labels.tolist() == [2, 2]


class RejectingWorker(FakeWorker):
    """Refuses every scan of 3 points, as a worker refuses a scan it cannot project."""

    def label_requests(self, requests):
        labels = super().label_requests(requests)
        return [
            "a laser id is off the image" if len(r.points) == 3 else out
            for r, out in zip(requests, labels, strict=True)
        ]


def test_batcher_refuses_one_scan_and_labels_the_rest_of_its_batch():
    async def run():
        worker = RejectingWorker(delay=0.01)
        batcher = ScanBatcher(worker, batch_size=4, max_wait=0.05)
        await batcher.start()
        try:
            return worker, await asyncio.gather(
                *(batcher.label_request(_request(n)) for n in (2, 3, 4)), return_exceptions=True
            )
        finally:
            await batcher.stop()

    worker, (two, three, four) = asyncio.run(run())
    assert worker.batches == [3] and worker.passes == [(3, True, False)]
    assert isinstance(three, ScanRejected) and "laser id" in str(three)
    assert two.labels.tolist() == [2, 2] and four.labels.tolist() == [4] * 4


def test_requests_for_confidences_never_share_a_pass_with_others():
    async def run():
        worker = FakeWorker(delay=0.02)
        batcher = ScanBatcher(worker, batch_size=8, max_wait=0.05)
        await batcher.start()
        try:
            results = await asyncio.gather(
                *(batcher.label_request(_request(n, confidence=n % 2 == 0)) for n in range(1, 9))
            )
        finally:
            await batcher.stop()
        return worker, results

    worker, results = asyncio.run(run())
    for n, labelled in enumerate(results, start=1):
        assert (labelled.confidence is not None) == (n % 2 == 0)
        if labelled.confidence is not None:
            assert labelled.confidence.shape == (n,)
    assert worker.batches == [8]  # one batch, one pass of each
    assert sorted(worker.passes) == [(4, True, False), (4, True, True)]


def test_options_group_in_the_order_they_first_came():
    requests = [_request(1, knn=k, confidence=c) for k, c in [(1, 0), (0, 0), (1, 0), (1, 1)]]
    assert group_by_options(requests) == [[0, 2], [1], [3]]
    assert group_by_options([]) == []
