"""A bounded worker pool: CPU work off the event loop, and a fast "busy" instead of a long queue.

Registrations take seconds of CPU; running them on the event loop would stall every other
request, and queueing them without bound would let latency grow without bound. :class:`WorkPool`
runs jobs on ``workers`` threads and admits at most ``workers + queue`` jobs at once; one more is
refused immediately with :class:`~catalign.api.errors.BusyError` (503 with ``Retry-After``).
A job whose caller went away before it started is dropped and gives its slot back.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

from catalign.api.errors import BusyError
from catalign.api.metrics import Metrics

T = TypeVar("T")
_SMOOTHING = 0.2  # weight of the latest job in the mean job duration


class WorkPool:
    """``workers`` threads, at most ``queue`` jobs waiting; ``run`` awaits a job's result."""

    def __init__(self, workers: int, queue: int, metrics: Metrics) -> None:
        self.workers = workers
        self.capacity = workers + queue
        self._metrics = metrics
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix="catalign-worker")
        self._lock = threading.Lock()
        self._admitted = 0
        self._running = 0
        self._mean_s = 1.0

    @property
    def full(self) -> bool:
        return self._admitted >= self.capacity

    def retry_after(self) -> int:
        """Seconds until a slot is likely free: the queue drained at the mean job duration."""
        return max(1, math.ceil(self._mean_s * self.capacity / self.workers))

    async def run(self, fn: Callable[..., T], *args: object) -> T:
        """Run ``fn(*args)`` on a worker; raise BusyError at once when no slot is free."""
        self._admit()
        try:
            future = self._executor.submit(self._job, fn, args)
        except BaseException:
            self._release()
            raise
        future.add_done_callback(lambda _: self._release())
        return await asyncio.wrap_future(future)

    def submit(self, fn: Callable[..., T], *args: object) -> Future[T]:
        """Run ``fn(*args)`` on a worker outside admission control (warm-up)."""
        return self._executor.submit(fn, *args)

    def shutdown(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)

    def ensure_capacity(self) -> None:
        """Raise BusyError now if a job would be refused (checked again on admission)."""
        if self.full:
            raise self._refuse()

    def _admit(self) -> None:
        with self._lock:
            if self._admitted >= self.capacity:
                raise self._refuse()
            self._admitted += 1
            self._publish()

    def _refuse(self) -> BusyError:
        self._metrics.rejected.inc()
        return BusyError(
            f"all {self.workers} workers are busy and {self.capacity - self.workers} "
            "requests are already waiting; retry later",
            retry_after=self.retry_after(),
        )

    def _job(self, fn: Callable[..., T], args: tuple[object, ...]) -> T:
        with self._lock:
            self._running += 1
            self._publish()
        started = time.perf_counter()
        try:
            return fn(*args)
        finally:
            elapsed = time.perf_counter() - started
            with self._lock:
                self._running -= 1
                self._mean_s += _SMOOTHING * (elapsed - self._mean_s)
                self._publish()

    def _release(self) -> None:
        with self._lock:
            self._admitted -= 1
            self._publish()

    def _publish(self) -> None:
        self._metrics.queue_depth.set(self._admitted - self._running)
        self._metrics.in_flight.set(self._running)
