"""Dynamic batching of single-scan requests in front of the in-process network.

Requests wait in one queue. Each dispatcher (one per model worker) takes the oldest request and up
to `batch_size - 1` more with the same options, waiting at most `max_wait` seconds after the oldest
arrived for the batch to fill, and awaits the pool on the whole batch. While a batch is in the
network, new requests gather, so under load batches fill without waiting. The event loop only
moves arrays around: the pool runs the network in a worker thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from rangeret.inference.results import ScanPrediction

log = logging.getLogger(__name__)


class ScanBackend(Protocol):
    """What the batcher needs from a pool (`service.local_labeller.LocalPool`)."""

    async def predict_async(
        self, scans: Sequence[np.ndarray], knn: bool = True, confidence: bool = False
    ) -> list[ScanPrediction | str]:
        """Each scan of a batch labelled (with confidences when asked), or the reason a scan
        cannot be labelled."""
        ...

    def queue_depth(self) -> int:
        """Batches sent and not answered yet."""
        ...


class BackendError(RuntimeError):
    """The labelling backend failed or cannot be reached (not the request's fault): 503, to be
    retried."""


class BackendTimeout(BackendError):
    """The labelling backend did not answer in time: 504."""


class ScanRejected(ValueError):
    """The workers cannot label this scan because of what it holds (a laser id off the image)."""


@dataclass
class _Request:
    points: np.ndarray
    options: tuple[bool, bool]  # (knn, confidence): requests share a batch only with equal ones
    arrived: float
    future: asyncio.Future[ScanPrediction]


class ScanBatcher:
    """Gathers concurrent single-scan requests into batches of at most `batch_size` for the pool."""

    def __init__(
        self,
        pool: ScanBackend,
        batch_size: int = 1,
        max_wait: float = 0.01,
        dispatchers: int = 1,
        on_batch: Callable[[int, float], None] | None = None,
    ) -> None:
        if batch_size < 1 or dispatchers < 1 or max_wait < 0:
            raise ValueError(
                "batch_size and dispatchers must be at least 1 and max_wait not negative"
            )
        self.pool = pool
        self.batch_size = batch_size
        self.max_wait = max_wait
        self.dispatchers = dispatchers
        self.on_batch = on_batch
        self._queue: deque[_Request] = deque()
        self._arrived = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []

    async def start(self) -> None:
        """Start the dispatchers (call from the serving event loop)."""
        self._tasks = [
            asyncio.create_task(self._dispatch(), name=f"batcher-{i}")
            for i in range(self.dispatchers)
        ]

    async def stop(self) -> None:
        """Stop the dispatchers and fail the requests still waiting."""
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks = []
        while self._queue:
            request = self._queue.popleft()
            if not request.future.done():
                request.future.set_exception(BackendError("the gateway is shutting down"))

    async def label(
        self, points: np.ndarray, knn: bool = True, confidence: bool = False
    ) -> ScanPrediction:
        """One scan (the profile's point records) labelled within a batch: raw labels (uint32,
        one per point) and, when asked, their confidences; `ScanRejected` when the workers refuse
        the scan itself."""
        loop = asyncio.get_running_loop()
        request = _Request(points, (knn, confidence), loop.time(), loop.create_future())
        self._queue.append(request)
        self._arrived.set()
        return await request.future

    def waiting(self) -> int:
        """Requests queued and not yet sent to the pool."""
        return len(self._queue)

    def depth(self) -> int:
        """Requests waiting plus batches in the workers: the gateway's queue depth."""
        return self.waiting() + self.pool.queue_depth()

    def _matching(self, options: tuple[bool, bool]) -> int:
        return sum(1 for r in self._queue if r.options == options and not r.future.done())

    def _take(self, options: tuple[bool, bool]) -> list[_Request]:
        """Remove and return up to `batch_size` live requests with these options, oldest first."""
        batch: list[_Request] = []
        kept: deque[_Request] = deque()
        while self._queue:
            request = self._queue.popleft()
            if request.future.done():
                continue  # its client went away
            if request.options == options and len(batch) < self.batch_size:
                batch.append(request)
            else:
                kept.append(request)
        self._queue = kept
        return batch

    async def _wait_for_arrival(self, timeout: float | None) -> bool:
        """Wait until a request arrives; False when `timeout` passed first."""
        self._arrived.clear()
        if timeout is None:
            await self._arrived.wait()
            return True
        try:
            await asyncio.wait_for(self._arrived.wait(), timeout)
        except asyncio.TimeoutError:
            return False
        return True

    async def _dispatch(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            while not self._queue:
                await self._wait_for_arrival(None)
            head = self._queue[0]
            deadline = head.arrived + self.max_wait
            while self._matching(head.options) < self.batch_size:
                remaining = deadline - loop.time()
                if remaining <= 0 or not await self._wait_for_arrival(remaining):
                    break
            batch = self._take(head.options)
            if batch:
                await self._run(batch, head.options, loop.time())

    async def _run(self, batch: list[_Request], options: tuple[bool, bool], sent: float) -> None:
        """Send one batch to the pool and hand each request its labels (or the failure)."""
        knn, confidence = options
        try:
            results = await self.pool.predict_async([r.points for r in batch], knn, confidence)
        except asyncio.CancelledError:
            for request in batch:
                if not request.future.done():
                    request.future.set_exception(BackendError("the gateway is shutting down"))
            raise
        except Exception as exc:
            log.exception("the worker backend failed on a batch of %d scans", len(batch))
            for request in batch:
                if not request.future.done():
                    request.future.set_exception(BackendError(f"the worker backend failed: {exc}"))
            return
        if self.on_batch is not None:
            self.on_batch(len(batch), asyncio.get_running_loop().time() - sent)
        for request, labels in zip(batch, results, strict=True):
            if request.future.done():
                continue
            if isinstance(labels, str):
                request.future.set_exception(ScanRejected(labels))
            else:
                request.future.set_result(labels)
