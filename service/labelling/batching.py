"""Single scans labelled in the gateway's own process, gathered into batches for one network.

`ScanBatcher` puts a request queue in front of a `rangeret.inference.scan_worker.ScanWorker`, so
that concurrent requests share network passes of up to `batch_size` scans. The worker's predictor
is the one the gateway's in-process jobs use: the network runs one pass at a time, so a scan
waits at most for the job batch in progress.

Requests wait in one queue. The dispatcher takes the oldest request and up to `batch_size - 1`
more, waiting at most `max_wait` seconds after the oldest arrived for the batch to fill, and
hands the whole batch to the scan worker in a worker thread; the worker runs one network pass per
set of equal options (`rangeret.inference.scan_worker.group_by_options`, as a Serve replica
does). While a batch is in the network, new requests gather, so under load batches fill without
waiting. The event loop only moves arrays around. The dispatcher runs while requests wait and
ends once none is left, so an idle batcher holds nothing on the event loop: a model's network is
gone as soon as the pool that evicted it and the requests it answered let go of it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from service.labelling.errors import BackendError, ScanRejected

if TYPE_CHECKING:
    from rangeret.inference.results import ScanPrediction
    from rangeret.inference.scan_worker import ScanRequest, ScanWorker

log = logging.getLogger(__name__)


@dataclass
class _Waiting:
    request: ScanRequest
    arrived: float
    future: asyncio.Future[ScanPrediction]


class ScanBatcher:
    """Gathers concurrent single-scan requests into batches of at most `batch_size` for the
    worker (whose network is loaded and warmed up before the batcher is built)."""

    def __init__(self, worker: ScanWorker, batch_size: int = 1, max_wait: float = 0.01) -> None:
        if batch_size < 1 or max_wait < 0:
            raise ValueError("batch_size must be at least 1 and max_wait not negative")
        self.worker = worker
        self.batch_size = batch_size
        self.max_wait = max_wait
        self.on_batch: Callable[[int, float], None] | None = None
        self._queue: deque[_Waiting] = deque()
        self._arrived = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._running = 0
        #: Whether requests are taken (between `start` and `stop`).
        self.accepting = False

    async def start(self, on_batch: Callable[[int, float], None] | None = None) -> None:
        """Take requests from now on (on the serving event loop); `on_batch(size, seconds)` is
        called after each batch."""
        self.on_batch = on_batch
        self.accepting = True

    async def stop(self) -> None:
        """Take no more requests, stop the dispatcher and fail the requests still waiting."""
        self.accepting = False
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        while self._queue:
            waiting = self._queue.popleft()
            if not waiting.future.done():
                waiting.future.set_exception(BackendError("the gateway is shutting down"))

    async def label_request(self, request: ScanRequest) -> ScanPrediction:
        """One scan labelled within a batch: raw labels (uint32, one per point) and, when asked,
        their confidences; `ScanRejected` when the worker refuses the scan itself, `BackendError`
        before `start` or after `stop`."""
        if not self.accepting:
            raise BackendError("the gateway is not taking scans now (starting or shutting down)")
        loop = asyncio.get_running_loop()
        waiting = _Waiting(request, loop.time(), loop.create_future())
        self._queue.append(waiting)
        self._arrived.set()
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._dispatch(), name="batcher")
        return await waiting.future

    def waiting(self) -> int:
        """Requests queued and not yet sent to the worker."""
        return len(self._queue)

    def depth(self) -> int:
        """Requests waiting plus batches in the worker: the gateway's queue depth."""
        return self.waiting() + self._running

    def _live(self) -> int:
        return sum(1 for w in self._queue if not w.future.done())

    def _take(self) -> list[_Waiting]:
        """Remove and return up to `batch_size` live requests, oldest first."""
        batch: list[_Waiting] = []
        while self._queue and len(batch) < self.batch_size:
            waiting = self._queue.popleft()
            if not waiting.future.done():  # else its client went away
                batch.append(waiting)
        return batch

    async def _wait_for_arrival(self, timeout: float) -> bool:
        """Wait until a request arrives; False when `timeout` passed first."""
        self._arrived.clear()
        try:
            await asyncio.wait_for(self._arrived.wait(), timeout)
        except asyncio.TimeoutError:
            return False
        return True

    async def _dispatch(self) -> None:
        """Send batches to the worker while requests wait; return once none is left."""
        loop = asyncio.get_running_loop()
        while self._queue:
            deadline = self._queue[0].arrived + self.max_wait
            while self._live() < self.batch_size:
                remaining = deadline - loop.time()
                if remaining <= 0 or not await self._wait_for_arrival(remaining):
                    break
            batch = self._take()
            if batch:
                await self._run(batch, loop.time())

    async def _run(self, batch: list[_Waiting], sent: float) -> None:
        """Send one batch to the worker and hand each request its labels (or the failure)."""
        self._running += 1
        try:
            results = await asyncio.to_thread(
                self.worker.label_requests, [w.request for w in batch]
            )
        except asyncio.CancelledError:
            for waiting in batch:
                if not waiting.future.done():
                    waiting.future.set_exception(BackendError("the gateway is shutting down"))
            raise
        except Exception as exc:
            log.exception("the worker backend failed on a batch of %d scans", len(batch))
            for waiting in batch:
                if not waiting.future.done():
                    waiting.future.set_exception(BackendError(f"the worker backend failed: {exc}"))
            return
        finally:
            self._running -= 1
        if self.on_batch is not None:
            self.on_batch(len(batch), asyncio.get_running_loop().time() - sent)
        for waiting, labels in zip(batch, results, strict=True):
            if waiting.future.done():
                continue
            if isinstance(labels, str):
                waiting.future.set_exception(ScanRejected(labels))
            else:
                waiting.future.set_result(labels)
