"""The single-scan request batcher: batches up to the batch size within the wait, backend
failures, refused scans, and requests for confidences kept apart."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from rangeret.inference.results import ScanPrediction
from service.batching import BackendError, ScanBatcher, ScanRejected


class FakePool:
    """Labels = the number of points, repeated; records every batch; can be told to fail."""

    def __init__(self, delay: float = 0.05) -> None:
        self.delay = delay
        self.batches: list[tuple[int, bool]] = []
        self.confidences: list[bool] = []
        self.fail = False
        self.in_flight = 0

    async def predict_async(self, scans, knn=True, confidence=False):
        self.batches.append((len(scans), knn))
        self.confidences.append(confidence)
        self.in_flight += 1
        try:
            await asyncio.sleep(self.delay)
            if self.fail:
                raise RuntimeError("actor died")
            return [
                ScanPrediction(
                    np.full(len(s), len(s) + (0 if knn else 1000), dtype=np.uint32),
                    np.full(len(s), 0.5, dtype=np.float32) if confidence else None,
                )
                for s in scans
            ]
        finally:
            self.in_flight -= 1

    def queue_depth(self):
        return self.in_flight


def _scan(n: int) -> np.ndarray:
    return np.zeros((n, 4), dtype=np.float32)


def test_batcher_gathers_concurrent_requests_up_to_the_batch_size():
    async def run():
        pool = FakePool()
        batcher = ScanBatcher(pool, batch_size=4, max_wait=0.05)
        await batcher.start()
        try:
            results = await asyncio.gather(
                *(batcher.label(_scan(n), knn=n % 2 == 0) for n in range(1, 12))
            )
        finally:
            await batcher.stop()
        return pool, results

    pool, results = asyncio.run(run())
    for n, labelled in enumerate(results, start=1):
        assert labelled.labels.tolist() == [n + (0 if n % 2 == 0 else 1000)] * n
        assert labelled.confidence is None
    assert all(size <= 4 for size, _ in pool.batches) and sum(s for s, _ in pool.batches) == 11
    assert max(size for size, _ in pool.batches) > 1 and len(pool.batches) < 11


def test_batcher_waits_at_most_max_wait_and_not_at_all_for_batch_size_one():
    async def one(batch_size: int) -> float:
        batcher = ScanBatcher(FakePool(delay=0), batch_size=batch_size, max_wait=0.2)
        await batcher.start()
        start = time.perf_counter()
        await batcher.label(_scan(3))
        elapsed = time.perf_counter() - start
        await batcher.stop()
        return elapsed

    assert 0.18 <= asyncio.run(one(4)) < 1.0
    assert asyncio.run(one(1)) < 0.1


def test_batcher_reports_backend_failures_and_keeps_serving():
    async def run():
        pool = FakePool(delay=0.01)
        batcher = ScanBatcher(pool, batch_size=2, max_wait=0.01)
        await batcher.start()
        pool.fail = True
        with pytest.raises(BackendError, match="actor died"):
            await batcher.label(_scan(2))
        pool.fail = False
        labels = await batcher.label(_scan(2))
        await batcher.stop()
        return labels

    assert asyncio.run(run()).labels.tolist() == [2, 2]


class RejectingPool(FakePool):
    """Refuses every scan of 3 points, as a worker refuses a scan it cannot project."""

    async def predict_async(self, scans, knn=True, confidence=False):
        labels = await super().predict_async(scans, knn, confidence)
        return [
            "a laser id is off the image" if len(s) == 3 else out
            for s, out in zip(scans, labels, strict=True)
        ]


def test_batcher_refuses_one_scan_and_labels_the_rest_of_its_batch():
    async def run():
        pool = RejectingPool(delay=0.01)
        batcher = ScanBatcher(pool, batch_size=4, max_wait=0.05)
        await batcher.start()
        try:
            return pool, await asyncio.gather(
                *(batcher.label(_scan(n)) for n in (2, 3, 4)), return_exceptions=True
            )
        finally:
            await batcher.stop()

    pool, (two, three, four) = asyncio.run(run())
    assert pool.batches == [(3, True)]
    assert isinstance(three, ScanRejected) and "laser id" in str(three)
    assert two.labels.tolist() == [2, 2] and four.labels.tolist() == [4] * 4


def test_batcher_never_mixes_requests_for_confidences_with_others():
    async def run():
        pool = FakePool(delay=0.02)
        batcher = ScanBatcher(pool, batch_size=8, max_wait=0.05)
        await batcher.start()
        try:
            results = await asyncio.gather(
                *(batcher.label(_scan(n), confidence=n % 2 == 0) for n in range(1, 9))
            )
        finally:
            await batcher.stop()
        return pool, results

    pool, results = asyncio.run(run())
    for n, labelled in enumerate(results, start=1):
        assert (labelled.confidence is not None) == (n % 2 == 0)
        if labelled.confidence is not None:
            assert labelled.confidence.shape == (n,)
    assert sorted(pool.confidences) == [False, True]  # one batch of each
